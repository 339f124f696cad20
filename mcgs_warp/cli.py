"""The ``mcgs-slam`` command line.

Bad input (:class:`mcgs_warp.errors.InputError`) is reported in one line naming the
file and field, with exit code 2 and no traceback; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import sys

from . import __version__


DEPTH_KINDS = ("exact", "mono", "none")
DEPTH_HELP = ("depth written beside the images: exact (ray-cast), mono (monocular-style: a smooth 0.8-1.25 scale "
              "field, noise, blurred edges; JDSA rescales it) or none; the exact depth always goes to gt/ for evaluation")


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
    synth.add_argument("--cameras", type=int, default=None, help="number of the built-in rig's cameras, 1-4 (default 3: front, left, right)")
    synth.add_argument("--rig", default=None, help="rig YAML to cast instead of the built-in rig (any cameras and models; body x forward, z up)")
    synth.add_argument("--frames", type=int, default=40, help="number of frames (default 40, at 10 Hz)")
    synth.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    synth.add_argument("--depth", choices=DEPTH_KINDS, default="exact", help=DEPTH_HELP)
    synth.add_argument("--scene", choices=("room", "indoor", "street"), default="room",
                       help="room (default: the built-in textured room), indoor (a room or corridor, its textures, light and the drive "
                       "through it all drawn from the seed) or street (a road between façades under a sky, depth 2 m to beyond 100 m, "
                       "10 m/s, with configs/rig_street.yaml: front, front-left, front-right)")
    synth.add_argument("--mono-prior", choices=("realistic", "smooth"), default="realistic",
                       help="with --depth mono, the prior's errors: realistic (default: a smooth scale field, per-object scale, depth-edge bleeding, "
                       "an affine error in inverse depth, a compressed far range) or smooth (the scale field alone, which JDSA's grids represent)")
    synth.add_argument("--realism", choices=("none", "camera"), default="camera",
                       help="camera (default): motion blur, vignetting, per-frame auto-exposure gains, shot and read noise, JPEG; none: the perfect render")
    synth.add_argument("--trajectory", choices=("forward", "loop"), default="forward",
                       help="forward (default: down the room with a weave, 1.5 m/s) or loop (one closed loop "
                       "through the room back to the start, so views are revisited; 0.55 m/s, the full 35.5 m loop from 640 frames, a shorter loop below)")
    synth.set_defaults(func=cmd_synth)

    demo = sub.add_parser(
        "demo",
        help="generate the synthetic 3-camera sequence and run the whole system on it",
        description="Write the built-in synthetic sequence to OUT/data and run SLAM on it with "
        "configs/synthetic.yaml; results go to OUT/run.",
    )
    demo.add_argument("--out", required=True, help="output folder")
    demo.add_argument("--frames", type=int, default=40, help="number of frames (default 40)")
    demo.add_argument("--cameras", type=int, default=3, help="number of rig cameras (default 3)")
    demo.add_argument("--depth", choices=DEPTH_KINDS, default="exact", help=DEPTH_HELP)
    demo.set_defaults(func=cmd_demo)

    run = sub.add_parser("run", help="run SLAM on a sequence folder (ours, EuRoC, KITTI odometry or TUM RGB-D)")
    run.add_argument("--data", required=True, help="sequence folder")
    run.add_argument("--out", required=True, help="output folder")
    run.add_argument("--config", default=None, help="run configuration YAML (default: configs/default.yaml)")
    run.add_argument("--cameras", default=None, help="comma-separated camera indices to use, e.g. 0,2 (default: all)")
    run.add_argument("--kitti-cameras", choices=("grey", "colour"), default="grey",
                     help="KITTI odometry folders: the grey pair image_0/image_1 (default) or the colour pair image_2/image_3")
    run.add_argument("--depth", choices=("auto", "sensor", "stereo", "none"), default=None,
                     help="depth source: sensor (the sequence's depth), stereo (sweep stereo between overlapping "
                     "cameras), none, or auto (default: sensor when every frame has depth, "
                     "else stereo when cameras overlap, else none)")
    run.add_argument("--correspondences", choices=("estimated", "ground-truth"), default=None,
                     help="estimated (default) or ground-truth: exact correspondences from the sequence's gt/ depth "
                     "and groundtruth.txt (synthetic sequences), to measure the back end without the front end")
    run.add_argument("--no-jdsa", action="store_true", help="disable joint depth-scale alignment")
    run.add_argument("--resume", action="store_true", help="continue an interrupted run from OUT/checkpoint.npz")
    run.set_defaults(func=cmd_run)

    ev = sub.add_parser("eval", help="ATE (Sim(3)-aligned) and RPE of a trajectory against ground truth")
    ev.add_argument("--est", required=True, help="estimated trajectory (TUM format)")
    ev.add_argument("--gt", required=True, help="ground-truth trajectory (TUM format)")
    ev.add_argument("--plot", default=None, help="write a top-view plot to this PNG")
    ev.add_argument("--json", default=None, help="write the metrics to this JSON file")
    ev.add_argument("--max-dt", type=float, default=0.02, help="timestamp association tolerance, s (default 0.02)")
    ev.add_argument("--no-scale", action="store_true", help="align with SE(3) instead of Sim(3)")
    ev.add_argument("--rpe-delta", type=int, default=1, help="RPE pose-pair spacing in matched poses (frames), as evo_rpe --delta (default 1)")
    ev.set_defaults(func=cmd_eval)

    ex = sub.add_parser("export", help="export a run's map to USD and/or 3DGS PLY")
    ex.add_argument("--run", required=True, help="run folder (holds map.ply, rig.yaml, keyframes.txt)")
    ex.add_argument("--usd", default=None, help="USD file to write (.usdc or .usda)")
    ex.add_argument("--ply", default=None, help="PLY file to write")
    ex.set_defaults(func=cmd_export)
    return parser


def cmd_synth(args) -> int:
    from .data.synthetic import generate

    from .errors import InputError
    from .rig import load_rig

    if args.rig is not None and args.cameras is not None:
        raise InputError(None, "--cameras", "takes the built-in rig's first cameras; with --rig, leave it out (the rig file says which cameras)")
    rig = load_rig(args.rig) if args.rig is not None else None
    seq = generate(args.out, n_cameras=3 if args.cameras is None else args.cameras, n_frames=args.frames, seed=args.seed, device=args.device, depth=args.depth, trajectory=args.trajectory, rig=rig, realism=args.realism, mono_prior=args.mono_prior, scene=args.scene)
    prior = f" ({args.mono_prior} errors)" if args.depth == "mono" else ""
    print(f"wrote {len(seq)} frames x {len(seq.rig)} cameras to {args.out} (depth: {args.depth}{prior}, realism: {args.realism})")
    return 0


def _print_metrics(metrics: dict) -> None:
    for key in ("ate_rmse_m", "ate_percent_of_path", "ate_se3_rmse_m", "sim3_scale", "path_length_m", "rpe_trans_m", "rpe_rot_deg", "psnr_db", "psnr_nonkeyframe_db", "ssim", "depth_l1_m", "n_gaussians", "n_keyframes", "seconds_total"):
        if metrics.get(key) is not None:
            v = metrics[key]
            print(f"  {key:<22} {v:.4f}" if isinstance(v, float) else f"  {key:<22} {v}")


def cmd_demo(args) -> int:
    from pathlib import Path

    from .data.synthetic import generate
    from .system.config import packaged_config
    from .system.run import run_sequence

    out = Path(args.out)
    generate(out / "data", n_cameras=args.cameras, n_frames=args.frames, seed=0, device=args.device, depth=args.depth)
    metrics = run_sequence(out / "data", out / "run", packaged_config("synthetic.yaml"), device=args.device)
    print(f"demo finished; outputs in {out / 'run'}")
    _print_metrics(metrics)
    return 0


def parse_cameras(text):
    from .errors import InputError

    if text is None:
        return None
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(None, "--cameras", f"expected comma-separated camera indices like 0,2, got {text!r}") from None


def cmd_run(args) -> int:
    from .system.run import run_sequence

    metrics = run_sequence(args.data, args.out, args.config, cameras=parse_cameras(args.cameras), kitti_cameras=args.kitti_cameras, jdsa=False if args.no_jdsa else None, depth=args.depth, correspondences=args.correspondences, device=args.device, resume=args.resume)
    print(f"run finished; outputs in {args.out}")
    _print_metrics(metrics)
    return 0


def cmd_eval(args) -> int:
    import json

    from .data.trajectory import read_tum
    from .eval.plots import plot_trajectory
    from .eval.trajectory import evaluate
    from .io import atomic_write

    from .errors import InputError

    if args.rpe_delta < 1:
        raise InputError(None, "--rpe-delta", f"expected at least 1 (frames), got {args.rpe_delta}")
    est = read_tum(args.est, min_poses=3)
    gt = read_tum(args.gt, min_poses=3)
    metrics, aligned, matched_gt, times = evaluate(est, gt, max_dt=args.max_dt, with_scale=not args.no_scale, rpe_delta=args.rpe_delta, return_timestamps=True)
    d = metrics.to_dict()
    for k, v in d.items():
        print(f"{k:<16} {v:.6f}" if isinstance(v, float) else f"{k:<16} {v}")
    if args.json:
        with atomic_write(args.json) as f:
            json.dump(d, f, indent=2)
    if args.plot:
        plot_trajectory(args.plot, aligned, matched_gt, times)  # the figure a run writes to plots/trajectory.png
    return 0


def cmd_export(args) -> int:
    from pathlib import Path

    from .data.trajectory import read_tum
    from .errors import InputError
    from .io.ply import read_ply, write_ply
    from .io.usd import write_usd
    from .rig import load_rig

    run = Path(args.run)
    if not (args.usd or args.ply):
        raise InputError(None, "--usd/--ply", "name at least one output file")
    params = read_ply(run / "map.ply")
    cams = []
    if (run / "rig.yaml").is_file() and (run / "keyframes.txt").is_file():
        rig = load_rig(run / "rig.yaml")
        kfs = read_tum(run / "keyframes.txt")
        cams = [(f"kf{k:03d}_{spec.name}", T @ spec.T_b_c, spec) for k, T in enumerate(kfs.poses) for spec in rig.cameras]
    if args.usd:
        write_usd(args.usd, params, cams)
        print(f"wrote {args.usd} ({len(params['means'])} Gaussians, {len(cams)} cameras)")
    if args.ply:
        write_ply(args.ply, params)
        print(f"wrote {args.ply}")
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
        hint = " (continue with --resume)" if args.command == "run" else ""
        print(f"mcgs-slam {args.command}: interrupted{hint}", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
