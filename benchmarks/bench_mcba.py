"""MCBA benchmark: time per iteration for 8 keyframes x 3 cameras at 1/8 resolution.

Builds the problem from the built-in synthetic sequence with exact correspondences
(tests/ba/problems.py), perturbs the poses (5 cm, 2 deg) and depths (10 %), and times
single LM iterations: the linearization kernel (with its host copies), the reduction
(pose blocks and Schur complement) and the solve (pose solve, back-substitution,
cost evaluation of the step). Prints medians over ``--repeats`` iterations.

    python benchmarks/bench_mcba.py [--device cuda:0] [--keyframes 8] [--stride 8]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "ba"))

from problems import Problem  # noqa: E402

from mcgs_warp.ba.mcba import MCBA, MCBAConfig  # noqa: E402
from mcgs_warp.data.synthetic import generate  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--keyframes", type=int, default=8)
    parser.add_argument("--stride", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    wp.set_device(args.device or wp.get_preferred_device())
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


if __name__ == "__main__":
    main()
