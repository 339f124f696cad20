"""A batch's child process: ``python -m mcgs_warp.system.batch_child ARGV`` is ``mcgs-slam ARGV``
ended by SIGTERM when the process that started it (a Ray worker) ends (Linux), so an
interrupted batch leaves no run behind (:mod:`.batch` starts it). Its own module, so that the
batch and the command line do not import each other."""

from __future__ import annotations

import contextlib
import os
import sys


def main(argv: list[str]) -> int:
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
        if os.getppid() == 1:  # the parent ended before the line above
            return 130
    from ..cli import main as cli_main

    return cli_main(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
