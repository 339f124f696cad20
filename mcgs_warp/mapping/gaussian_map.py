"""The 3D Gaussian map: parameters on a Warp device plus an anchor keyframe per Gaussian.

New Gaussians come from back-projected keyframe depth (every ``stride``-th pixel),
coloured from the image, isotropic with a scale of half the mean distance to their 3
nearest neighbours (SciPy ``cKDTree``; neighbouring splats then meet at about one
sigma), unit rotation and opacity 0.9 (logit). Each
Gaussian remembers the keyframe it was created from, so when tracking moves that
keyframe its Gaussians move with it (paper eq. 12-13).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels import Gaussians

INITIAL_OPACITY = 0.9
MAX_INITIAL_SCALE = 0.5  # m


def logit(p):
    return np.log(p / (1.0 - p))


class GaussianMap:
    def __init__(self, device=None):
        self.device = wp.get_device(device)
        self.gaussians = Gaussians.from_numpy(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), self.device)
        self.anchors = np.zeros(0, np.int32)  # keyframe id per Gaussian
        self._anchors_dev = None

    def __len__(self) -> int:
        return self.gaussians.n

    # ----------------------------------------------------------------------------------
    def to_numpy(self) -> dict:
        g = self.gaussians
        return {
            "means": g.means.numpy().copy(),
            "quats": g.quats.numpy().copy(),
            "log_scales": g.log_scales.numpy().copy(),
            "opacity_logits": g.opacity_logits.numpy().copy(),
            "colors": g.colors.numpy().copy(),
            "anchors": self.anchors.copy(),
        }

    def set_numpy(self, d: dict) -> None:
        self.gaussians = Gaussians.from_numpy(d["means"], d["quats"], d["log_scales"], d["opacity_logits"], d["colors"], self.device)
        self.anchors = np.asarray(d["anchors"], np.int32)
        self._anchors_dev = None

    def append(self, means, colors, log_scales, anchor: int, quats=None, opacity_logits=None) -> int:
        n = len(means)
        quats = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)) if quats is None else quats
        opacity_logits = np.full(n, logit(INITIAL_OPACITY)) if opacity_logits is None else opacity_logits
        d = self.to_numpy()
        new = {"means": means, "quats": quats, "log_scales": log_scales, "opacity_logits": opacity_logits, "colors": colors, "anchors": np.full(n, anchor, np.int32)}
        self.set_numpy({k: np.concatenate([d[k], np.asarray(new[k], dtype=d[k].dtype)]) for k in d})
        return n

    def keep(self, mask: np.ndarray) -> int:
        """Keep the Gaussians where ``mask`` is true; returns how many were removed."""
        d = self.to_numpy()
        self.set_numpy({k: v[mask] for k, v in d.items()})
        return int((~mask).sum())

    # ----------------------------------------------------------------------------------
    def insert_from_depth(self, rig, T_w_b, images, depths, anchor: int, stride: int = 4, mask=None, max_depth: float = 50.0) -> int:
        """Back-project every ``stride``-th pixel with depth of each camera (``mask[c]``
        [H,W] bool limits to unobserved pixels) into new Gaussians anchored to ``anchor``."""
        from scipy.spatial import cKDTree

        from ..ba.graph import unproject_pixels

        pts, cols = [], []
        for c, spec in enumerate(rig.cameras):
            d = depths[c]
            if d is None:
                continue
            o = stride // 2
            v, u = np.mgrid[o : spec.height : stride, o : spec.width : stride]
            z = d[v, u]
            ok = (z > 0) & (z < max_depth)
            if mask is not None and mask[c] is not None:
                ok &= mask[c][v, u]
            if not ok.any():
                continue
            uv = np.stack([u[ok], v[ok]], 1).astype(np.float64)
            X_c = unproject_pixels(spec.warp_camera(), uv) * z[ok][:, None]
            T = T_w_b @ spec.T_b_c
            pts.append(X_c @ T[:3, :3].T + T[:3, 3])
            cols.append(images[c][v[ok], u[ok]])
        if not pts:
            return 0
        pts = np.concatenate(pts)
        cols = np.concatenate(cols)
        existing = self.gaussians.means.numpy() if len(self) else np.zeros((0, 3))
        tree = cKDTree(np.concatenate([existing, pts]))
        dist, _ = tree.query(pts, k=4)
        scale = np.clip(0.5 * dist[:, 1:].mean(1), 1e-4, MAX_INITIAL_SCALE)
        return self.append(pts, cols, np.log(np.repeat(scale[:, None], 3, 1)), anchor)

    def move_anchored(self, keyframe: int, delta: np.ndarray, scale: float = 1.0) -> None:
        """Eq. 12-13: apply the world-frame correction ``delta`` (4x4, x <- delta x) to the
        Gaussians anchored to ``keyframe``; multiply their scales by ``scale``."""
        from ..kernels.mapping import move_anchored_kernel

        if len(self) == 0:
            return
        if self._anchors_dev is None:
            self._anchors_dev = wp.array(self.anchors, dtype=wp.int32, device=self.device)
        g = self.gaussians
        wp.launch(
            move_anchored_kernel,
            dim=len(self),
            inputs=[g.means, g.quats, g.log_scales, self._anchors_dev, int(keyframe), wp.mat44(*np.asarray(delta, np.float32).ravel()), float(np.log(scale))],
            device=self.device,
        )

    def scale_anchored(self, keyframe: int, T_w_b: np.ndarray, scale: float) -> None:
        """Eq. 13: scale the Gaussians anchored to ``keyframe`` by ``scale`` about its rig
        origin (positions and sizes), after its depth was rescaled by that factor."""
        from ..kernels.mapping import scale_anchored_kernel

        if len(self) == 0:
            return
        if self._anchors_dev is None:
            self._anchors_dev = wp.array(self.anchors, dtype=wp.int32, device=self.device)
        g = self.gaussians
        wp.launch(scale_anchored_kernel, dim=len(self), inputs=[g.means, g.log_scales, self._anchors_dev, int(keyframe), wp.vec3(*np.asarray(T_w_b, np.float32)[:3, 3]), float(scale)], device=self.device)

    def follow_keyframes(self, old_T_w_b: np.ndarray, new_T_w_b: np.ndarray, scale: float = 1.0) -> None:
        """Move every keyframe's Gaussians from its old to its new rig pose."""
        for k, (A, B) in enumerate(zip(old_T_w_b, new_T_w_b)):
            if not np.allclose(A, B, atol=1e-9):
                self.move_anchored(k, B @ np.linalg.inv(A), scale)
