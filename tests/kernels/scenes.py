"""Small random scenes and cameras shared by the kernel tests."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from mcgs_warp.kernels import make_camera

W, H = 64, 48


def cameras():
    """One camera of each model (name -> Camera), small images."""
    return {
        "pinhole": make_camera("pinhole", W, H, (50.0, 52.0, 31.5, 23.0), (-0.12, 0.03, 0.001, -0.002, 0.005)),
        "fisheye": make_camera("fisheye", W, H, (30.0, 30.5, 32.0, 24.2), (0.05, -0.01, 0.004, -0.001)),
        "equirectangular": make_camera("equirectangular", W, H),
    }


def random_pose(rng, angle=0.3, shift=0.5):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * angle).as_matrix()
    T[:3, 3] = rng.normal(size=3) * shift
    return T


def random_scene(rng, n, model, T_w_c, depth=(1.5, 4.0), scale=(0.03, 0.25)):
    """``n`` Gaussians in front of the camera ``T_w_c`` (within its field of view)."""
    if model == "equirectangular":
        lon = rng.uniform(-np.pi, np.pi, n) * 0.9
        lat = rng.uniform(-1.2, 1.2, n)
        dirs = np.stack([np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)], 1)
    else:
        half = 0.55 if model == "pinhole" else 0.9
        dirs = np.stack([rng.uniform(-half, half, n), rng.uniform(-half * 0.75, half * 0.75, n), np.ones(n)], 1)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pc = dirs * rng.uniform(*depth, n)[:, None]
    means = pc @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    quats = rng.normal(size=(n, 4))
    log_scales = np.log(rng.uniform(*scale, (n, 3)))
    logits = rng.normal(0.5, 1.5, n)
    colors = rng.uniform(0, 1, (n, 3))
    return means, quats, log_scales, logits, colors
