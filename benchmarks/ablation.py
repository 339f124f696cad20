"""Ablation on the synthetic sequence: 1 vs 3 cameras, with and without JDSA.

    python benchmarks/ablation.py [--frames 40] [--out out/ablation]

Prints ATE (Sim(3)-aligned, and as % of the path), the Sim(3) scale, PSNR and run time
per variant. Note: the synthetic sequence gives exact depth, which JDSA leaves
unscaled (it is for monocular-style priors), so the two JDSA rows agree.
"""

import argparse
from pathlib import Path

import warp as wp

from mcgs_warp.data.synthetic import generate
from mcgs_warp.system.config import load_run_config, packaged_config
from mcgs_warp.system.run import run_sequence

VARIANTS = [("1 camera (front)", [0], True), ("3 cameras", None, True), ("3 cameras, no JDSA", None, False)]

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--out", default="out/ablation")
    parser.add_argument("--device", default=None)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    out = Path(args.out)
    generate(out / "data", n_cameras=3, n_frames=args.frames, device=args.device, progress=False)
    rows = []
    for name, cams, jdsa in VARIANTS:
        cfg = load_run_config(packaged_config("synthetic.yaml"))
        m = run_sequence(out / "data", out / name.replace(" ", "_").replace(",", "").replace("(", "").replace(")", ""), cfg, cameras=cams, jdsa=jdsa, device=args.device, progress=False)
        rows.append((name, m))
        print(f"done: {name}", flush=True)
    print()
    print(f"{'variant':<22} {'ATE cm':>8} {'ATE %path':>10} {'scale':>7} {'PSNR dB':>8} {'seconds':>8}")
    for name, m in rows:
        print(f"{name:<22} {100 * m['ate_rmse_m']:>8.2f} {m['ate_percent_of_path']:>10.2f} {m['sim3_scale']:>7.3f} {m['psnr_db']:>8.2f} {m['seconds_total']:>8.0f}")
