"""Real data, one table: the default system, its keypoint odometry alone and the classical VO
on every real sequence, at every frame step.

    python benchmarks/real.py [DATA ...] [--out out/real] [--every 1 2 3] [--frames A:B]
        [--config C.yaml] [--classical ../shared/tools/classical_vo.py] [--no-classical]

DATA: sequence folders (default: every folder in ../shared/data). For each folder and frame
step (``--every``; 2 and 3 are the frame-dropped variants), in a fresh process each:

- **ours**: ``mcgs-slam run --data DATA --out OUT/<name>/e<N> --every N`` (default configuration
  unless ``--config``), scored from its ``trajectory.txt`` and ``metrics.json``;
- **odometry**: the same run's keypoint odometry alone (``trajectory_odometry.txt``, every frame it
  placed): the sparse core the default must not fall behind;
- **classical**: the classical stereo / RGB-D visual odometry (``../shared/tools/classical_vo.py``)
  on the same frames, where it applies (a KITTI stereo folder, or one camera with depth: a TUM
  RGB-D folder, or ours); its row says why where it does not.

Every trajectory is scored the same way against the sequence's ground truth: SE(3)- and
Sim(3)-aligned ATE, the Sim(3) scale (applied to the estimate: below 1 is a path too long), the
path ratio (estimated over true path length) and its range over segments of 10 processed frames
(a metric-scale bias shows in every segment, noise does not). Ours adds tracking failures, PSNR on
keyframes and on held-out frames, and where the sequence has exact depth (``gt/`` of a LiDAR) per
camera the rendered depth's median relative error, the share of exact-depth pixels it covers and
the median on the pixels its confidence marks measured. Wall time and peak memory are each
process's own (``os.wait4``). Nothing else should run on the cores meanwhile: the times are
what a user measures. Prints a Markdown table (docs/results.md's real-data section) and writes it
with every figure to OUT/real.md and OUT/real.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared"
SEGMENT = 10  # processed frames per segment of the step ratios


def timed(cmd, log: Path) -> tuple[int, float, float]:
    """Run ``cmd`` with its output to ``log``: exit code, wall seconds, its own peak memory (GB)."""
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    return os.waitstatus_to_exitcode(status), time.perf_counter() - t0, usage.ru_maxrss / 1024**2


def figures(est, gt) -> dict:
    """ATE (SE(3), Sim(3)), scale, path ratio and its range over segments of ``SEGMENT`` poses
    of trajectory ``est`` against ``gt`` (both :class:`~mcgs_warp.data.trajectory.Trajectory`)."""
    from mcgs_warp.eval.trajectory import associate, evaluate

    se3 = evaluate(est, gt, with_scale=False)[0]
    sim3 = evaluate(est, gt, with_scale=True)[0]
    i, j = associate(est.timestamps, gt.timestamps)
    de = np.linalg.norm(np.diff(est.positions[i], axis=0), axis=1)
    dg = np.linalg.norm(np.diff(gt.positions[j], axis=0), axis=1)
    segs = [de[s : s + SEGMENT].sum() / dg[s : s + SEGMENT].sum() for s in range(0, len(dg), SEGMENT) if dg[s : s + SEGMENT].sum() > 0]
    return {"se3_m": se3.ate_rmse_m, "se3_percent": 100 * se3.ate_rmse_m / max(se3.path_length_m, 1e-12), "sim3_m": sim3.ate_rmse_m, "scale": sim3.scale,
            "path_ratio": float(de.sum() / max(dg.sum(), 1e-12)), "segments": [round(float(s), 4) for s in segs], "path_m": se3.path_length_m, "poses": int(len(i))}


def classical_input(seq, data: Path, frames: list[int], tmp: Path) -> tuple[Path | None, str]:
    """A folder the classical VO reads holding ``frames`` of ``data`` (KITTI: links to its images;
    one camera with depth: our folder format, depth in mm, with the ground truth per frame),
    or None and why it does not apply."""
    import cv2

    if seq.groundtruth is None:
        return None, "no ground truth to score it against"
    if (data / "image_0").is_dir() and (data / "image_1").is_dir() and (data / "calib.txt").is_file():
        from mcgs_warp.data.kitti import find_poses

        for cam in ("image_0", "image_1"):
            files = sorted((data / cam).glob("*.png"))
            (tmp / cam).mkdir(parents=True)
            for n, f in enumerate(frames):
                (tmp / cam / f"{n:06d}.png").symlink_to(files[f].resolve())
        shutil.copy(data / "calib.txt", tmp / "calib.txt")
        poses = [line for line in find_poses(data).read_text().splitlines() if line.strip()]
        (tmp / "poses.txt").write_text("".join(poses[f] + "\n" for f in frames))
        return tmp, ""
    if len(seq.rig) == 1 and any(seq.depth_cameras()):
        from mcgs_warp.data.trajectory import nearest_timestamps
        from mcgs_warp.geometry import matrix_to_quat

        spec = seq.rig.cameras[0]
        if spec.model != "pinhole" or spec.distortion and any(spec.distortion):
            return None, "the classical VO takes an undistorted pinhole camera"
        j = nearest_timestamps(np.asarray(seq.timestamps)[frames], seq.groundtruth.timestamps, 0.02)
        import yaml

        (tmp / "cam0" / "rgb").mkdir(parents=True)
        (tmp / "cam0" / "depth").mkdir(parents=True)
        (tmp / "rig.yaml").write_text(yaml.safe_dump({"cameras": [{"intrinsics": [float(v) for v in spec.intrinsics]}]}))
        rows = []
        for n, (f, g) in enumerate(zip(frames, j)):
            if g < 0:
                continue  # the classical VO scores by index: frames without ground truth stay out
            fr = seq[f]
            cv2.imwrite(str(tmp / "cam0" / "rgb" / f"{n:06d}.png"), cv2.cvtColor(np.clip(fr.images[0] * 255 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(tmp / "cam0" / "depth" / f"{n:06d}.png"), np.clip(fr.depths[0] * 1000 + 0.5, 0, 65535).astype(np.uint16))
            T = seq.groundtruth.poses[g] @ spec.T_b_c  # the classical VO's world-from-camera
            rows.append(f"{seq.timestamps[f]:.6f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *matrix_to_quat(T[:3, :3]))))
        (tmp / "groundtruth.txt").write_text("\n".join(rows) + "\n")
        return tmp, ""
    return None, "no stereo pair in the classical VO's layout, and no single depth camera"


def classical_trajectory(est_file: Path, tmp: Path, seq, frames: list[int]):
    """The classical VO's estimate (KITTI rows of T_w_cam0) as our rig body's poses at the frames
    it ran (a KITTI rig's body is camera 0; one depth camera's is where its T_b_c says)."""
    from mcgs_warp.data.trajectory import Trajectory

    A = np.loadtxt(est_file).reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (len(A), 1, 1))
    T[:, :3] = A
    stamps = np.asarray(seq.timestamps)[frames]
    if (tmp / "groundtruth.txt").is_file():  # one camera with depth: the frames that had ground truth
        stamps = np.loadtxt(tmp / "groundtruth.txt", ndmin=2)[:, 0]
        T = T @ np.linalg.inv(seq.rig.cameras[0].T_b_c)
    return Trajectory(stamps[: len(T)], T[: len(stamps)])


def run_one(data: Path, every: int, frames_arg: str | None, args) -> list[dict]:
    from mcgs_warp.data import open_sequence
    from mcgs_warp.data.sequence import parse_frames
    from mcgs_warp.data.trajectory import read_tum

    name = data.name
    seq = open_sequence(data)
    a, b = parse_frames(frames_arg)
    frames = list(range(len(seq)))[a:b:every]
    out = args.out / name / f"e{every}"
    rows = []
    if len(frames) < 3:  # an ATE needs three poses
        return [{"sequence": name, "every": every, "frames": len(frames), "method": "ours", "skipped": f"every {every} keeps {len(frames)} of its {len(seq)} frames (an ATE needs 3)"}]
    print(f"{name} every {every}: ours ...", file=sys.stderr, flush=True)
    cmd = [sys.executable, "-m", "mcgs_warp", "run", "--data", str(data), "--out", str(out), "--every", str(every)]
    cmd += ["--frames", frames_arg] if frames_arg else []
    cmd += ["--config", str(args.config)] if args.config else []
    rc, wall, gb = timed(cmd, out / "run.log")
    base = {"sequence": name, "every": every, "frames": len(frames)}
    if rc != 0:
        rows.append({**base, "method": "ours", "error": f"exit {rc}: see {out / 'run.log'}"})
    else:
        m = json.loads((out / "metrics.json").read_text())
        ours = {**base, "method": "ours", **figures(read_tum(out / "trajectory.txt"), seq.groundtruth), "failures": m["tracking_failures"],
                "psnr_kf": m["psnr_db"], "psnr_held_out": m.get("psnr_nonkeyframe_db"), "depth": m.get("depth_vs_exact_per_camera"), "seconds": wall, "peak_gb": gb}
        rows.append(ours)
        if (out / "trajectory_odometry.txt").is_file():
            rows.append({**base, "method": "odometry", **figures(read_tum(out / "trajectory_odometry.txt"), seq.groundtruth)})
    if args.no_classical:
        return rows
    if not args.classical.is_file():
        rows.append({**base, "method": "classical", "skipped": f"{args.classical} not found"})
        return rows
    with tempfile.TemporaryDirectory() as t:
        tmp, why = classical_input(seq, data, frames, Path(t) / name)
        if tmp is None:
            rows.append({**base, "method": "classical", "skipped": why})
            return rows
        print(f"{name} every {every}: classical VO ...", file=sys.stderr, flush=True)
        est = args.out / name / f"e{every}_classical.txt"
        rc, wall, gb = timed([sys.executable, str(args.classical), str(tmp), "--out", str(est)], args.out / name / f"e{every}_classical.log")
        if rc != 0:
            rows.append({**base, "method": "classical", "error": f"exit {rc}: see {est.with_suffix('.log')}"})
        else:
            rows.append({**base, "method": "classical", **figures(classical_trajectory(est, tmp, seq, frames), seq.groundtruth), "seconds": wall, "peak_gb": gb})
    return rows


def cell(v, fmt: str) -> str:
    return "–" if v is None else format(v, fmt)


def table(rows: list[dict]) -> str:
    lines = ["| sequence | every | method | SE(3) ATE | Sim(3) ATE | scale | path ratio | 10-frame segments | failures | PSNR kf / held-out | depth vs exact: median rel. / covered / measured px (per camera) | s | peak GB |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|"]
    for r in rows:
        head = f"| {r['sequence']} | {r['every']} | {r['method']} |"
        if "se3_m" not in r:
            lines.append(head + f" {r.get('skipped') or r.get('error')} |" + " |" * 9)
            continue
        segs = f"{min(r['segments']):.4f}-{max(r['segments']):.4f}" if r["segments"] else "–"
        depth = "–"
        if r.get("depth"):
            depth = ", ".join(f"{cam} {cell(d['median_rel'] and 100 * d['median_rel'], '.1f')} % / {100 * d['coverage']:.0f} % / {cell(d['median_rel_measured'] and 100 * d['median_rel_measured'], '.1f')} %" for cam, d in r["depth"].items())
        psnr = f"{r['psnr_kf']:.2f} / {cell(r['psnr_held_out'], '.2f')}" if "psnr_kf" in r else "–"
        lines.append(head + f" {r['se3_m']:.3f} m ({r['se3_percent']:.2f} %) | {r['sim3_m']:.3f} m | {r['scale']:.4f} | {r['path_ratio']:.4f} | {segs} | {r.get('failures', '–')} | {psnr} | {depth} | "
                     f"{cell(r.get('seconds'), '.0f')} | {cell(r.get('peak_gb'), '.2f')} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="*", type=Path, help="sequence folders (default: every folder in ../shared/data)")
    ap.add_argument("--out", type=Path, default=Path("out/real"))
    ap.add_argument("--every", type=int, nargs="+", default=[1], help="frame steps: 1 (all frames), 2 and 3 (the frame-dropped variants)")
    ap.add_argument("--frames", default=None, metavar="A:B", help="run frames A to B of each sequence (run --frames)")
    ap.add_argument("--config", type=Path, default=None, help="run configuration (default: the default)")
    ap.add_argument("--classical", type=Path, default=SHARED / "tools" / "classical_vo.py", help="the classical VO script")
    ap.add_argument("--no-classical", action="store_true", help="skip the classical VO")
    args = ap.parse_args()
    data = args.data
    if not data and (SHARED / "data").is_dir():
        data = sorted(p for p in (SHARED / "data").iterdir() if p.is_dir())
    if not data:
        print(f"no real sequences given and none at {SHARED / 'data'} (their licences keep them out of the repository): nothing to measure")
        return 0
    rows = []
    for d in data:
        for every in args.every:
            rows += run_one(d, every, args.frames, args)
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / "real.json").write_text(json.dumps(rows, indent=1))
    text = table(rows)
    (args.out / "real.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
