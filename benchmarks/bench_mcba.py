"""MCBA benchmark: time per iteration for a local window, and time and memory of a
global-BA-sized problem.

Table 1, local window: 8 keyframes x 3 cameras at 1/8 resolution, built from the
built-in synthetic sequence with exact correspondences (tests/ba/problems.py); the
poses are perturbed (5 cm, 2 deg) and the depths (10 %), and single LM iterations are
timed: the linearization kernel, the reduction (pose blocks and sparse Schur
complement) and the solve (pose solve, back-substitution, cost evaluation of the
step). Medians over ``--repeats`` iterations.

Table 2, global BA (``--global-keyframes``, e.g. 100,300; 0 skips it): a loop of
keyframes x 3 cameras (the synthetic rig and its loop trajectory) inside a box room,
each grid pixel's point at a random depth in front of the walls, so every
correspondence is exact (the room is convex: nothing occludes); temporal radius
``--radius`` plus cross-view edges, 40x30 grid. Each size runs in a fresh subprocess:
the median of ``--repeats`` single LM iterations, the wall time of one solve of
``--global-iterations`` iterations (the offline global BA), and the peak resident
memory of the process (``VmHWM``; Warp's CPU arrays live outside Python's
allocator) and its growth during the solves over the built problem.

    python benchmarks/bench_mcba.py [--device cuda:0] [--keyframes 8] [--stride 8] [--global-keyframes 100,300]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
import tempfile
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "ba"))

from problems import Problem  # noqa: E402

from mcgs_warp.ba.mcba import MCBA, MCBAConfig  # noqa: E402
from mcgs_warp.data.synthetic import generate  # noqa: E402


def local_window(args):
    with tempfile.TemporaryDirectory() as tmp:
        seq = generate(Path(tmp) / "seq", n_cameras=3, n_frames=2 * args.keyframes, seed=0, progress=False)
        P = Problem(seq, list(range(0, 2 * args.keyframes, 2)), stride=args.stride)
    rng = np.random.default_rng(0)
    rows = []
    for rep in range(args.repeats + 1):  # the first is a warm-up (kernel compilation)
        P.perturb(rng)
        stats = MCBA(P.buf, MCBAConfig(iterations=1)).solve(P.edges, P.targets, P.weights)
        if rep:
            rows.append((stats.seconds_kernel, stats.seconds_reduce, stats.seconds_solve))
    k, r, s = np.median(np.array(rows), axis=0)
    pixels = P.buf.h * P.buf.w
    print(f"device: {wp.get_device()}; {args.keyframes} keyframes x 3 cameras; grid {P.buf.w}x{P.buf.h} (1/{args.stride});")
    print(f"{len(P.edges)} edges ({int((P.edges[:, 4] == 0).sum())} temporal, {int((P.edges[:, 4] == 1).sum())} cross-view), {len(P.edges) * pixels} residual pixels")
    print(f"median of {args.repeats} LM iterations, seconds")
    print(f"{'kernel':>10} {'reduction':>10} {'solve':>10} {'total':>10}")
    print(f"{k:>10.4f} {r:>10.4f} {s:>10.4f} {k + r + s:>10.4f}")


# ---- global BA -------------------------------------------------------------------------
def memory_kib(field: str) -> int:
    """``VmHWM`` (peak) or ``VmRSS`` of this process, KiB (Linux)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def reset_peak_memory() -> bool:
    """Reset ``VmHWM`` to the current RSS (Linux ``clear_refs``); False where not allowed."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def room_problem(n_keyframes: int, radius: int, rng):
    """A loop of ``n_keyframes`` x 3 cameras in a box room with exact correspondences:
    (buffer at the true state, edges [E,5], targets [E,h,w,2], weights [E,h,w])."""
    from mcgs_warp.ba.edges import build_edges, camera_overlap
    from mcgs_warp.buffer import KeyframeBuffer
    from mcgs_warp.data.synthetic import loop_trajectory, synthetic_rig
    from mcgs_warp.kernels import reference

    rig = synthetic_rig(3)
    buf = KeyframeBuffer(rig, stride=8, capacity=n_keyframes)
    T_w_b = loop_trajectory(n_keyframes, max_step=np.inf).poses  # the full room loop
    lo = T_w_b[:, :3, 3].min(0) - [3.0, 3.0, 1.4]  # walls 3 m beside the path, floor 1.4 m below
    hi = T_w_b[:, :3, 3].max(0) + [3.0, 3.0, 1.6]
    rays = buf.rays.numpy().astype(np.float64)  # [C,h,w,3] unit-depth rays
    for k, T in enumerate(T_w_b):
        disp = np.zeros((len(rig), buf.h, buf.w))
        for c, spec in enumerate(rig.cameras):
            T_w_c = T @ spec.T_b_c
            d = rays[c] @ T_w_c[:3, :3].T  # world direction per unit of camera depth
            with np.errstate(divide="ignore"):
                exit_ = np.where(d > 0, (hi - T_w_c[:3, 3]) / d, (lo - T_w_c[:3, 3]) / d)
            z = np.where(np.isfinite(exit_) & (exit_ > 0), exit_, np.inf).min(-1)  # camera depth of the wall
            disp[c] = 1.0 / (z * rng.uniform(0.6, 1.0, z.shape))  # a point in front of it
        buf.add(k, 0.1 * k, [None] * len(rig), T, disp)
    edges = build_edges(range(n_keyframes), len(rig), camera_overlap(rig), radius=radius, cross_view=True)
    targets = np.zeros((len(edges), buf.h, buf.w, 2), np.float32)
    weights = np.zeros((len(edges), buf.h, buf.w), np.float32)
    points = rays / buf.disp.numpy()[:n_keyframes, ..., None]  # [K,C,h,w,3] camera frame, m
    cams = [spec.warp_camera() for spec in buf.reduced]
    for e, (i, ci, j, cj) in enumerate(edges[:, :4]):
        T = np.linalg.inv(T_w_b[j] @ rig.cameras[cj].T_b_c) @ T_w_b[i] @ rig.cameras[ci].T_b_c
        X = points[i, ci] @ T[:3, :3].T + T[:3, 3]
        ok = reference.in_domain(cams[cj], X)
        uv = reference.project(cams[cj], np.where(ok[..., None], X, [0.0, 0.0, 1.0]))
        ok &= np.all((uv >= 0) & (uv <= [cams[cj].width - 1, cams[cj].height - 1]), -1)  # a convex room: nothing occludes
        targets[e] = uv
        weights[e] = ok
    return buf, edges, targets, weights


def global_ba_row(args, n_keyframes: int) -> dict:
    """One row of table 2 (run in a fresh process)."""
    from mcgs_warp.geometry import se3_exp

    rng = np.random.default_rng(0)
    buf, edges, targets, weights = room_problem(n_keyframes, args.radius, rng)
    T = buf.get_poses()
    steps = np.concatenate([rng.normal(scale=0.01, size=(len(T), 3)), rng.normal(scale=np.radians(0.3), size=(len(T), 3))], 1)
    steps[0] = 0.0
    buf.set_poses(T @ se3_exp(steps))
    start = buf.disp.numpy() * np.exp(0.05 * rng.normal(size=buf.disp.shape)).astype(np.float32), buf.poses.numpy()
    warm = (edges[:, 0] < 2) & (edges[:, 2] < 2)  # kernel compilation on a two-keyframe window
    MCBA(buf, MCBAConfig(iterations=1)).solve(edges[warm], targets[warm], weights[warm])
    buf.disp.assign(start[0])
    buf.poses.assign(start[1])
    built = memory_kib("VmRSS")
    reset = reset_peak_memory()
    rows = []
    for _ in range(args.repeats):
        stats = MCBA(buf, MCBAConfig(iterations=1)).solve(edges, targets, weights)
        rows.append((stats.seconds_kernel, stats.seconds_reduce, stats.seconds_solve))
    buf.disp.assign(start[0])
    buf.poses.assign(start[1])
    t0 = time.perf_counter()
    stats = MCBA(buf, MCBAConfig(iterations=args.global_iterations)).solve(edges, targets, weights)
    wall = time.perf_counter() - t0
    return dict(
        keyframes=n_keyframes,
        edges=len(edges),
        cross=int((edges[:, 0] == edges[:, 2]).sum()),
        pixels=len(edges) * buf.h * buf.w,
        split=np.median(rows, axis=0).tolist(),
        solve=wall,
        iterations=len(stats.cost) - 1,
        cost_ratio=stats.cost[-1] / stats.cost[0],
        peak_mib=memory_kib("VmHWM") / 1024,
        solve_growth_mib=(memory_kib("VmHWM") - built) / 1024 if reset else float("nan"),
        grid=f"{buf.w}x{buf.h}",
    )


def global_ba(args):
    sizes = [int(k) for k in args.global_keyframes.split(",") if int(k) > 0]
    if not sizes:
        return
    out = []
    for n in sizes:  # a fresh process per size: its peak memory is this problem's alone
        cmd = [sys.executable, __file__, "--global-row", str(n), "--radius", str(args.radius), "--repeats", str(args.repeats), "--global-iterations", str(args.global_iterations)]
        if args.device:
            cmd += ["--device", args.device]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode:
            sys.exit(f"global BA row {n} failed:\n{res.stderr}")
        out.append(json.loads(res.stdout.strip().splitlines()[-1]))
    print()
    print(f"global BA: loop x 3 cameras, grid {out[0]['grid']}, temporal radius {args.radius} + cross-view edges; seconds per LM iteration (median of {args.repeats}),")
    print(f"one solve of {args.global_iterations} iterations, peak resident memory of the process and its growth during the solves")
    print("(s/iter: kernel + reduction + solve, as in table 1)")
    print(f"{'keyframes':>9} {'edges':>6} {'cross':>6} {'res. pixels':>11} {'kernel':>7} {'reduce':>7} {'solve':>7} {'s/iter':>7} {'solve s':>8} {'accepted':>8} {'cost ratio':>10} {'peak MiB':>9} {'growth MiB':>10}")
    for r in out:
        k, red, sol = r["split"]
        print(
            f"{r['keyframes']:>9} {r['edges']:>6} {r['cross']:>6} {r['pixels']:>11} {k:>7.2f} {red:>7.2f} {sol:>7.2f} {k + red + sol:>7.2f} {r['solve']:>8.2f} "
            f"{r['iterations']:>8} {r['cost_ratio']:>10.2e} {r['peak_mib']:>9.0f} {r['solve_growth_mib']:>10.0f}"
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--keyframes", type=int, default=8, help="table 1 (0: skip)")
    parser.add_argument("--stride", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--global-keyframes", default="0", help="table 2 sizes, comma-separated (e.g. 100,300; 0: skip)")
    parser.add_argument("--global-iterations", type=int, default=4, help="LM iterations of the timed global solve (the system's default)")
    parser.add_argument("--radius", type=int, default=2, help="table 2: temporal edge radius")
    parser.add_argument("--global-row", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    wp.set_device(args.device or wp.get_preferred_device())
    if args.global_row:
        print(json.dumps(global_ba_row(args, args.global_row)))
        return
    if args.keyframes:
        local_window(args)
    global_ba(args)


if __name__ == "__main__":
    main()
