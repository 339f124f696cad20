"""Splatting benchmark: project / sort / blend / backward times on the current Warp device.

Scene: N Gaussians spread uniformly through the frustum of a 640x480 pinhole camera
between 2 and 12 m, scales 1-5 cm, random rotations, opacities sigmoid(N(0.5, 1)) and
colours, so the image is covered many times over (as a mapped scene is). Prints the
median of ``--repeats`` runs after a warm-up, and the speed ratio of the Warp renderer
over the NumPy reference on a small scene.

    python benchmarks/bench_render.py [--device cuda:0] [--sizes 10000 100000 300000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import warp as wp

from mcgs_warp.kernels import Gaussians, Views, bin_tiles, blend, make_camera, project, reference, render, render_backward


def frustum_scene(n: int, cam, rng, depth=(2.0, 12.0), scale=(0.01, 0.05)):
    z = rng.uniform(*depth, n)
    u = rng.uniform(-20, cam.width + 20, n)
    v = rng.uniform(-20, cam.height + 20, n)
    means = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
    return (
        means,
        rng.normal(size=(n, 4)),
        np.log(rng.uniform(*scale, (n, 3))),
        rng.normal(0.5, 1.0, n),
        rng.uniform(0, 1, (n, 3)),
    )


def timed(fn, repeats: int, device) -> tuple[float, object]:
    out = fn()  # warm-up (compiles kernels on first use)
    wp.synchronize_device(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 300_000])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    device = wp.get_device(args.device)
    rng = np.random.default_rng(0)
    cam = make_camera("pinhole", 640, 480, (525.0, 525.0, 319.5, 239.5), (-0.05, 0.01, 0.0, 0.0, 0.0))
    views = Views.create([cam], np.eye(4)[None], device)

    print(f"device: {device} ({device.name}); image 640x480; median of {args.repeats} runs, seconds")
    print(f"{'N':>8} {'list/tile':>9} {'project':>8} {'sort':>8} {'blend':>8} {'forward':>8} {'backward':>9}")
    for n in args.sizes:
        g = Gaussians.from_numpy(*frustum_scene(n, cam, rng), device=device)
        t_proj, proj = timed(lambda: project(g, views), args.repeats, device)
        t_sort, bins = timed(lambda: bin_tiles(proj, views), args.repeats, device)
        t_blend, out = timed(lambda: blend(proj, bins, g.colors, views), args.repeats, device)
        t_fwd, out = timed(lambda: render(g, views), args.repeats, device)
        grad = wp.array(np.full((1, 480, 640, 3), 1e-3, np.float32), dtype=wp.vec3, device=device)
        t_bwd, _ = timed(lambda: render_backward(g, views, out, grad_color=grad), args.repeats, device)
        pairs = out.bins.count / (views.tiles_x * views.tiles_y)
        print(f"{n:>8} {pairs:>9.1f} {t_proj:>8.4f} {t_sort:>8.4f} {t_blend:>8.4f} {t_fwd:>8.4f} {t_bwd:>9.4f}")

    # Against the NumPy reference on a small scene.
    small = make_camera("pinhole", 160, 120, (130.0, 130.0, 79.5, 59.5), (-0.05, 0.01, 0.0, 0.0, 0.0))
    scene = frustum_scene(2000, small, rng)
    sv = Views.create([small], np.eye(4)[None], device)
    sg = Gaussians.from_numpy(*scene, device=device)
    t_warp, _ = timed(lambda: render(sg, sv), args.repeats, device)
    t0 = time.perf_counter()
    reference.render(*scene, small, np.eye(4))
    t_ref = time.perf_counter() - t0
    print()
    print(f"{'small scene (2000 Gaussians, 160x120)':<40} {'seconds':>8}")
    print(f"{'NumPy reference render':<40} {t_ref:>8.4f}")
    print(f"{'Warp render (median)':<40} {t_warp:>8.4f}")
    print(f"{'speed-up':<40} {t_ref / t_warp:>7.0f}x")


if __name__ == "__main__":
    main()
