"""The one error type for bad user input.

Readers, config loaders and the CLI raise :class:`InputError` with a message that
names the file, the field and what was expected, e.g.
``configs/rig.yaml: cameras[1].intrinsics: expected 4 numbers, got 3``. The CLI
prints it without a traceback and exits non-zero.
"""

from __future__ import annotations

import os
import sys


class InputError(ValueError):
    """Malformed or missing input; the message is meant for the user."""

    def __init__(self, source, field: str | None, message: str):
        self.source = os.fspath(source) if source is not None else None
        self.field = None if field is None else str(field)  # a YAML key may be a number
        where = ": ".join(p for p in (self.source, self.field) if p)
        super().__init__(f"{where}: {message}" if where else message)


def warn(source, message: str) -> None:
    """One warning line on stderr, ``warning: <source>: <message>`` (input that reads, but oddly)."""
    where = f"{os.fspath(source)}: " if source is not None else ""
    print(f"warning: {where}{message}", file=sys.stderr)
