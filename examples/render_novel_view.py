"""Render a saved map from a new viewpoint: a keyframe's pose moved sideways and turned.

    python examples/render_novel_view.py out/synthetic/run --keyframe 3 --shift 0.3 --yaw 10 --out novel.png

Reads ``map.ply``, ``rig.yaml`` and ``keyframes.txt`` from the run folder and writes
colour | depth of every rig camera at the new pose.
"""

import argparse
from pathlib import Path

import numpy as np
import warp as wp

from mcgs_warp.data.trajectory import read_tum
from mcgs_warp.geometry import yaw_pitch_roll
from mcgs_warp.io import write_image
from mcgs_warp.io.ply import read_ply
from mcgs_warp.kernels import Gaussians, Views, render
from mcgs_warp.rig import load_rig
from mcgs_warp.system.outputs import depth_colormap


def render_novel(run: Path, keyframe: int, shift: float, yaw_deg: float, device=None) -> np.ndarray:
    params = read_ply(run / "map.ply")
    rig = load_rig(run / "rig.yaml")
    T_w_b = read_tum(run / "keyframes.txt").poses[keyframe]
    move = np.eye(4)
    move[:3, :3] = yaw_pitch_roll(np.radians(yaw_deg))
    move[1, 3] = shift  # body y: to the left
    g = Gaussians.from_numpy(params["means"], params["quats"], params["log_scales"], params["opacity_logits"], params["colors"], device)
    out = render(g, Views.create(rig.warp_cameras(), rig.camera_poses(T_w_b @ move), device))
    col, dep = out.color.numpy(), out.depth.numpy()
    rows = []
    for c, spec in enumerate(rig.cameras):
        d = dep[c, : spec.height, : spec.width]
        vmax = float(np.percentile(d[d > 0], 95)) if (d > 0).any() else 1.0
        rows.append(np.concatenate([np.clip(col[c, : spec.height, : spec.width], 0, 1), depth_colormap(d, vmax)], 1))
    width = max(r.shape[1] for r in rows)
    return np.concatenate([np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows], 0)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", help="run folder")
    parser.add_argument("--keyframe", type=int, default=0)
    parser.add_argument("--shift", type=float, default=0.3, help="m to the left of the keyframe")
    parser.add_argument("--yaw", type=float, default=10.0, help="degrees to the left")
    parser.add_argument("--out", default="novel_view.png")
    parser.add_argument("--device", default=None)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    write_image(args.out, render_novel(Path(args.run), args.keyframe, args.shift, args.yaw, args.device))
    print(f"wrote {args.out}")
