"""The ``mcgs-slam`` command line.

Bad input (:class:`mcgs_warp.errors.InputError`) is reported in one line naming the
file and field, with exit code 2 and no traceback; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import sys

from . import __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mcgs-slam",
        description="Multi-camera Gaussian-Splatting SLAM on NVIDIA Warp.",
    )
    parser.add_argument("--version", action="version", version=f"mcgs-slam {__version__}")
    parser.add_argument("--debug", action="store_true", help="show Python tracebacks on errors")
    parser.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: Warp's default)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    synth = sub.add_parser(
        "synth",
        help="generate the built-in synthetic multi-camera sequence",
        description="Ray-cast a textured room from a moving rig and write RGB, exact depth, rig.yaml, "
        "timestamps.txt and groundtruth.txt in our folder format.",
    )
    synth.add_argument("--out", required=True, help="output folder")
    synth.add_argument("--cameras", type=int, default=3, help="number of rig cameras, 1-4 (default 3: front, left, right)")
    synth.add_argument("--frames", type=int, default=40, help="number of frames (default 40, at 10 Hz)")
    synth.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    synth.set_defaults(func=cmd_synth)
    return parser


def cmd_synth(args) -> int:
    from .data.synthetic import generate

    seq = generate(args.out, n_cameras=args.cameras, n_frames=args.frames, seed=args.seed, device=args.device)
    print(f"wrote {len(seq)} frames x {len(seq.rig)} cameras to {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    from .errors import InputError

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    if not args.debug:
        import warp as wp

        wp.config.log_level = wp.LOG_WARNING  # no start-up banner or per-module load lines
    try:
        return args.func(args)
    except InputError as e:
        if args.debug:
            raise
        print(f"mcgs-slam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mcgs-slam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
