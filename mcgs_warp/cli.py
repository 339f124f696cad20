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


def _add_sequence_arguments(p) -> None:
    """The options ``run`` and ``map`` share: input, output, configuration, cameras, depth."""
    p.add_argument("--data", required=True, help="sequence folder, ROS 1 .bag file or ROS 2 bag folder")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", default=None, help="run configuration YAML (default: configs/default.yaml)")
    p.add_argument("--cameras", default=None, help="comma-separated camera indices to use, e.g. 0,2 (default: all)")
    p.add_argument("--kitti-cameras", choices=("grey", "colour", "all"), default="grey",
                     help="KITTI odometry folders: the grey pair image_0/image_1 (default), the colour pair image_2/image_3, or all four as one rig")
    p.add_argument("--segment", default=None, metavar="NAME",
                     help="Waymo Open Dataset v2 folders: the segment (context name); nuScenes: the scene, e.g. scene-0061 (default: the only one)")
    p.add_argument("--waymo-cameras", choices=("front3", "all"), default="front3",
                     help="Waymo Open Dataset folders: front3 (default: FRONT_LEFT, FRONT, FRONT_RIGHT) or all five cameras")
    p.add_argument("--depth", choices=("auto", "sensor", "stereo", "none"), default=None,
                     help="depth source: sensor (the sequence's depth), stereo (sweep stereo between overlapping "
                     "cameras), none, or auto (default: sensor when every frame has depth, "
                     "else stereo when cameras overlap, else none)")
    p.add_argument("--correspondences", choices=("estimated", "ground-truth", "none"), default=None,
                     help="estimated (default), ground-truth: exact correspondences from the sequence's gt/ depth "
                     "and groundtruth.txt (synthetic sequences), to measure the back end without the front end, or none: "
                     "no dense correspondences, keypoint tracks alone (the sparse core, to measure what the dense edges add)")
    p.add_argument("--no-jdsa", action="store_true", help="disable joint depth-scale alignment")
    p.add_argument("--every", type=int, default=1, metavar="N",
                     help="keep every N-th frame (default 1: all): a high-rate camera at a lower rate; frame numbers in messages count the kept frames")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="run frames A to B of the sequence (B exclusive, either may be left out; default: all), before --every")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run from OUT/checkpoint.npz")
    calib = p.add_mutually_exclusive_group()
    calib.add_argument("--rig", default=None, help="rig YAML (or Kalibr camchain): a ROS bag's calibration, each camera with its topic:; "
                       "for a folder it replaces the folder's calibration (same cameras and resolutions)")
    calib.add_argument("--from-kalibr", default=None, metavar="CAMCHAIN", help="Kalibr camchain.yaml / camchain-imucam.yaml as the rig (topics from its rostopic:)")
    p.add_argument("--sync-tolerance", type=float, default=None, metavar="S",
                     help="ROS bags: images of the cameras within this many seconds are one frame (default 0.005)")


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

    run = sub.add_parser("run", help="run SLAM on a sequence folder (ours, EuRoC, KITTI odometry or TUM RGB-D) or a ROS bag")
    _add_sequence_arguments(run)
    run.set_defaults(func=cmd_run)

    mp = sub.add_parser("map", help="map a sequence from given rig poses (GNSS/INS, LiDAR, ground truth): depth, Gaussians and refinement, no tracking")
    _add_sequence_arguments(mp)
    mp.add_argument("--poses", required=True, help="TUM trajectory of the rig body (t tx ty tz qx qy qz qw), or 'groundtruth': the sequence's own")
    mp.add_argument("--refine-poses", action="store_true", help="let the final refinement adjust the given poses (default: held)")
    mp.set_defaults(func=cmd_run)

    shared = argparse.ArgumentParser(add_help=False)
    _add_sequence_arguments(shared)  # run's options; batch redefines --data, --out and --resume below
    bt = sub.add_parser("batch", parents=[shared], conflict_handler="resolve", help="run many sequences on Ray, one run per sequence, with a summary",
                        description="Run SLAM on many sequences, each one Ray task running `mcgs-slam run --data SEQ --out OUT/<sequence>` with the options below "
                        "in a child process; a failed sequence is reported and the others go on (exit code 1 if any failed). OUT/<sequence>/batch.json records a "
                        "finished run's configuration hash: running the same command again skips what finished and runs the rest. At the end "
                        "OUT/summary.csv, summary.md and summary.png compare the runs; OUT/logs/<sequence>.log hold their output. Needs Ray: pip install \"mcgs_warp[cluster]\".")
    bt.add_argument("inputs", nargs="*", metavar="DATA", help="a sequence (folder or ROS bag), a text file listing sequences (one a line, # comments, "
                    "paths relative to the file) or a folder of sequences (its subfolders and bags that look like sequences); a Waymo Open Dataset v2 "
                    "folder or a nuScenes root is one run per segment or scene (run --segment NAME), into OUT/<segment>")
    bt.add_argument("--data", action="extend", nargs="+", default=[], metavar="DATA", help="more inputs, as the positional ones")
    bt.add_argument("--out", required=True, help="output folder: OUT/<sequence>/ per sequence (its folder or bag name), OUT/summary.*")
    bt.add_argument("--segment", default=None, metavar="NAME", help="Waymo and nuScenes folders: run this segment or scene alone (default: every one)")
    bt.add_argument("--resume", action="store_true", help="each unfinished run continues from its OUT/<sequence>/checkpoint.npz (run --resume); finished ones are skipped anyway")
    bt.add_argument("--address", default=None, help="Ray cluster: auto (the one `ray start` runs on this machine) or ray://HOST:10001 (Ray Client, pip install \"ray[client]\"); "
                    "default: a local Ray instance with this machine's cores")
    bt.add_argument("--cpus-per-run", type=float, default=1.0, metavar="N", help="CPUs Ray reserves for each run (default 1)")
    bt.add_argument("--gpus-per-run", type=float, default=0.0, metavar="N", help="GPUs Ray reserves for each run, e.g. 1 or 0.5 (default 0: the runs use the CPU unless --device says otherwise)")
    bt.set_defaults(func=cmd_batch)

    rg = sub.add_parser("rig", help="convert a Kalibr calibration into a rig YAML",
                        description="Read a Kalibr camchain.yaml or camchain-imucam.yaml (pinhole-radtan, pinhole-equi) and write our rig YAML: "
                        "body = IMU when cam0 has T_cam_imu, else cam0; timeshift_cam_imu becomes time_offset; rostopic becomes topic.")
    rg.add_argument("--from-kalibr", required=True, metavar="CAMCHAIN", help="Kalibr camchain YAML")
    rg.add_argument("--out", required=True, help="rig YAML to write")
    rg.set_defaults(func=cmd_rig)

    bg = sub.add_parser("bag", help="write a sequence as a ROS bag (with a rig.yaml naming its topics)",
                        description="Write any sequence we read (e.g. the synthetic one) as OUT/recording.bag (ROS 1) or OUT/recording/ (ROS 2), "
                        "one sensor_msgs/Image topic per camera, plus OUT/rig.yaml with the topics and OUT/groundtruth.txt where the sequence has one.")
    bg.add_argument("--data", required=True, help="sequence folder")
    bg.add_argument("--out", required=True, help="output folder (must not hold a recording yet)")
    bg.add_argument("--ros2", action="store_true", help="write a ROS 2 bag (sqlite3) instead of ROS 1")
    bg.add_argument("--compressed", action="store_true", help="sensor_msgs/CompressedImage (lossless PNG) instead of raw rgb8 Image messages")
    bg.set_defaults(func=cmd_bag)

    vw = sub.add_parser("view", help="serve an interactive 3D web viewer of a run folder",
                        description="Serve the run's Gaussians (as splats), keyframe cameras with their images, the trajectory and ground truth "
                        "on http://HOST:PORT; on a remote machine forward the port (ssh -L 8080:localhost:8080 host) and open it locally.")
    vw.add_argument("run", help="run folder (map.ply, trajectory.txt, keyframes.txt, rig.yaml)")
    vw.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    vw.add_argument("--host", default="127.0.0.1", help="interface to listen on (default 127.0.0.1: this machine only)")
    vw.add_argument("--max-gaussians", type=int, default=500_000, help="show at most this many Gaussians, the most opaque (default 500000)")
    vw.set_defaults(func=cmd_view)

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
    from .data.sequence import parse_frames
    from .system.run import run_sequence

    rig = args.rig
    if args.from_kalibr is not None:
        from .data.kalibr import rig_from_kalibr

        rig_from_kalibr(args.from_kalibr)  # refuses a file that is not a camchain
        rig = args.from_kalibr  # run_sequence reads it again, and names it in its errors
    metrics = run_sequence(args.data, args.out, args.config, cameras=parse_cameras(args.cameras), kitti_cameras=args.kitti_cameras, jdsa=False if args.no_jdsa else None, depth=args.depth, correspondences=args.correspondences, device=args.device, resume=args.resume, rig=rig, sync_tolerance=args.sync_tolerance, every=args.every, frames=parse_frames(args.frames),
                           poses=getattr(args, "poses", None), refine_poses=getattr(args, "refine_poses", False), segment=args.segment, waymo_cameras=args.waymo_cameras)
    print(f"{args.command} finished; outputs in {args.out}")
    _print_metrics(metrics)
    return 0


def cmd_batch(args) -> int:
    from .system.batch import RayMissing, RunOptions, run_batch

    shared = argparse.ArgumentParser(add_help=False)
    _add_sequence_arguments(shared)
    defaults = vars(shared.parse_args(["--data", "-", "--out", "-"]))  # run's defaults; argparse names --kitti-cameras kitti_cameras
    options = RunOptions(tuple((f"--{dest.replace('_', '-')}", getattr(args, dest)) for dest, default in defaults.items()
                               if dest not in ("data", "out") and getattr(args, dest) != default), args.device)  # what differs goes to every run
    try:
        results = run_batch([*args.inputs, *args.data], args.out, options, address=args.address, cpus_per_run=args.cpus_per_run, gpus_per_run=args.gpus_per_run,
                            echo=lambda line: print(line, flush=True))
    except RayMissing as e:
        print(f"mcgs-slam batch: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mcgs-slam batch: interrupted (run the same command again: finished sequences are skipped)", file=sys.stderr)
        return 130
    failed = [r["name"] for r in results if r["status"] == "failed"]
    ran = sum(r["status"] == "ok" for r in results)
    print(f"batch finished: {ran} run, {len(results) - ran - len(failed)} skipped, {len(failed)} failed{' (' + ', '.join(failed) + ')' if failed else ''}; "
          f"summary in {args.out}/summary.md")
    return 1 if failed else 0


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


def cmd_rig(args) -> int:
    import numpy as np

    from .data.kalibr import rig_from_kalibr
    from .rig import save_rig

    rig = rig_from_kalibr(args.from_kalibr)
    save_rig(rig, args.out)
    print(f"wrote {args.out}: {len(rig)} cameras")
    for c in rig.cameras:
        t = c.T_b_c[:3, 3]
        print(f"  {c.name:<8} {c.model:<9} {c.width}x{c.height}  at ({t[0]:+.4f}, {t[1]:+.4f}, {t[2]:+.4f}) m  |t| {np.linalg.norm(t):.4f} m"
              + (f"  topic {c.topic}" if c.topic else "") + (f"  time_offset {c.time_offset:+.6f} s" if c.time_offset else ""))
    return 0


def cmd_bag(args) -> int:
    from pathlib import Path

    from .data import open_sequence, write_tum
    from .data.rosbag import write_bag
    from .errors import InputError
    from .rig import save_rig

    out = Path(args.out)
    bag = out / ("recording" if args.ros2 else "recording.bag")
    if bag.exists():
        raise InputError(bag, None, "already exists: choose another --out (a recording is never overwritten)")
    seq = open_sequence(args.data)
    out.mkdir(parents=True, exist_ok=True)
    path, rig = write_bag(seq, bag, ros=2 if args.ros2 else 1, compressed=args.compressed)
    save_rig(rig, out / "rig.yaml")
    if seq.groundtruth is not None:
        write_tum(out / "groundtruth.txt", seq.groundtruth)
    print(f"wrote {path} ({len(seq)} frames x {len(rig)} cameras) and {out / 'rig.yaml'}")
    print(f"  run it: mcgs-slam run --data {path} --rig {out / 'rig.yaml'} --out RUN")
    return 0


def cmd_view(args) -> int:
    from .viewer import serve

    serve(args.run, host=args.host, port=args.port, max_gaussians=args.max_gaussians)
    return 0


#: commands that run Warp kernels in this process (``batch`` runs them in its children)
WARP_COMMANDS = ("run", "map", "demo", "synth", "export")
CUDA_DRIVER_LINE = "Could not find or load the NVIDIA CUDA driver"


def init_warp(device=None, quiet: bool = True) -> str:
    """Initialize Warp. Warp's native start-up prints a CUDA-driver warning on every machine
    without a GPU; ``quiet`` keeps that line (and only that line) from the terminal. Returns
    the device that runs the kernels, in words (``main`` says it once, when the command is done)."""
    import os
    import tempfile

    import warp as wp

    if quiet:
        sys.stderr.flush()
        with tempfile.TemporaryFile(mode="w+b") as tmp:
            saved = os.dup(2)
            os.dup2(tmp.fileno(), 2)
            try:
                wp.init()
            finally:
                os.dup2(saved, 2)
                os.close(saved)
            tmp.seek(0)
            rest = [line for line in tmp.read().decode(errors="replace").splitlines() if line.strip() and CUDA_DRIVER_LINE not in line and line.strip() != "available."]
        for line in rest:
            print(line, file=sys.stderr)
    else:
        wp.init()
    try:
        name = str(wp.get_device(device))
    except (ValueError, RuntimeError):
        from .errors import InputError

        devices = ", ".join(str(d) for d in wp.get_devices())
        raise InputError(None, "--device", f"expected a Warp device of this machine ({devices}), got {device!r}") from None
    why = "" if wp.is_cuda_available() else " (no CUDA driver: GPU execution is not available)"
    return f"{name}{why}"


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
        device = init_warp(getattr(args, "device", None), quiet=not args.debug) if args.command in WARP_COMMANDS else None
        rc = args.func(args)
        if device is not None and not rc:  # said once, after the work (an error stays one line)
            print(f"mcgs-slam {args.command}: Warp kernels ran on {device}", file=sys.stderr)
        return rc
    except InputError as e:
        if args.debug:
            raise
        print(f"mcgs-slam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        hint = " (continue with --resume)" if args.command in ("run", "map") else ""
        print(f"mcgs-slam {args.command}: interrupted{hint}", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
