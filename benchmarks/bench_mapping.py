"""Mapping benchmark: iterations per second and memory for 3 cameras x 10 keyframes.

Builds a map from the built-in synthetic sequence (320x240, or ``--width`` px wide with the
rig's cameras resampled; keyframes every 2nd
frame, Gaussians from the true depth every 4th pixel), then times mapping
iterations (one keyframe = 3 views per iteration), split into render, loss
(device kernels: exposure, L1 + SSIM, depth, normal, and their gradients), backward
(adjoints, scale regularizer, finiteness check) and optimizer (Adam + densification
statistics). Prints medians over ``--iterations`` after a warm-up, beside the renderer's own
forward + backward time for the same views and Gaussians (colour gradient already on the
device; timed right after each iteration, so that both see the same machine load) and the
ratio (what the mapping stage adds on top of splatting; target <= 1.5).

    python benchmarks/bench_mapping.py [--device cuda:0] [--keyframes 10] [--width 640]
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "ba"))

from problems import Problem  # noqa: E402

from mcgs_warp.data.synthetic import generate  # noqa: E402
from mcgs_warp.mapping.mapper import Mapper, MappingConfig  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--keyframes", type=int, default=10)
    parser.add_argument("--iterations", type=int, default=30)
    parser.add_argument("--width", type=int, default=320, help="image width, px (the rig's 320x240 cameras resampled; 640: a KITTI-sized mapping problem)")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    wp.set_device(args.device or wp.get_preferred_device())
    with tempfile.TemporaryDirectory() as tmp:
        from mcgs_warp.data.resample import resampled_camera
        from mcgs_warp.data.synthetic import synthetic_rig
        from mcgs_warp.rig import Rig

        rig = synthetic_rig(3)
        rig = Rig([resampled_camera(c, args.width, round(c.height * args.width / c.width)) for c in rig.cameras])
        seq = generate(Path(tmp) / "seq", n_frames=2 * args.keyframes, seed=0, progress=False, rig=rig)
        frames = list(range(0, 2 * args.keyframes, 2))
        P = Problem(seq, frames, cross_view=False)
        m = Mapper(P.buf, config=MappingConfig(densify_every=0))
        for k, f in enumerate(frames):
            m.add_keyframe(k, seq[f].depths)
    m.optimize(3)  # warm-up: kernel compilation
    import time

    from mcgs_warp.kernels import render, render_backward

    # Mapping iterations interleaved with the renderer alone (forward + backward of a colour
    # gradient) on the same keyframe's views and Gaussians, so both see the same machine load.
    keys = sorted(m.buf.targets)
    views = m.views(keys[0])
    grad_color = wp.array(np.ones((views.n, views.height, views.width, 3), np.float32), dtype=wp.vec3)
    rows, totals, times = [], [], []
    for i in range(args.iterations):
        k = keys[i % len(keys)]
        before = dict(m.seconds)
        t0 = time.perf_counter()
        m.step(k)
        wp.synchronize()
        totals.append(time.perf_counter() - t0)
        rows.append([m.seconds[key] - before[key] for key in ("render", "loss", "backward", "optimizer")])
        views = m.views(k)
        t0 = time.perf_counter()
        out = render(m.map.gaussians, views)
        render_backward(m.map.gaussians, views, out, grad_color=grad_color)
        wp.synchronize()
        times.append(time.perf_counter() - t0)
    r = np.median(np.array(rows), axis=0)
    total, renderer = float(np.median(totals)), float(np.median(times))
    per_iteration = float(np.median(np.array(totals) / np.array(times)))
    n = len(m.map)
    param_mb = n * (3 + 4 + 3 + 1 + 3) * 4 / 2**20
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    spec = m.buf.rig.cameras[0]
    print(f"device: {wp.get_device()}; {args.keyframes} keyframes x 3 cameras at {spec.width}x{spec.height}; {n} Gaussians")
    print(f"median of {args.iterations} iterations (one keyframe, 3 views each), seconds")
    print(f"{'render':>9} {'loss':>9} {'backward':>9} {'optimizer':>9} {'total':>9} {'it/s':>7} {'renderer f+b':>13} {'ratio':>6} {'ratio/it':>9}")
    print(f"{r[0]:>9.4f} {r[1]:>9.4f} {r[2]:>9.4f} {r[3]:>9.4f} {total:>9.4f} {1 / total:>7.2f} {renderer:>13.4f} {total / renderer:>6.2f} {per_iteration:>9.2f}")
    print("total: median iteration time; ratio: total / renderer f+b; ratio/it: median of the per-iteration ratios")
    print(f"memory: parameters {param_mb:.1f} MB, with Adam moments {3 * param_mb:.1f} MB; peak process RSS {rss_mb:.0f} MB")


if __name__ == "__main__":
    main()
