"""The MCBA edge graph: which (keyframe, camera) views are linked by correspondences.

An edge ``(i, ci, j, cj)`` predicts pixels of view (i, ci) in view (j, cj) through the
single formula ``T_cj_ci = inv(T_b_cj) inv(T_w_bj) T_w_bi T_b_ci`` (DESIGN.md):

* temporal edges: same camera, keyframes up to ``radius`` apart (paper eq. 7);
* cross-view edges: same keyframe, cameras whose fields of view overlap (eq. 8;
  the rig pose cancels, the known baseline fixes the metric scale);
* cross-camera-and-time edges (optional): overlapping cameras at nearby keyframes.

Edges come in both directions, so every view's depth is constrained by its neighbours.
"""

from __future__ import annotations

import numpy as np

from ..buffer import grid_pixels
from ..rig import Rig

TEMPORAL, CROSS_VIEW, CROSS_TIME = 0, 1, 2


def camera_overlap(rig: Rig, depth: float = 5.0, stride: int = 8) -> np.ndarray:
    """Fraction [C,C] of camera a's pixels that camera b sees when the scene lies at
    ``depth`` metres (a rough, rig-only test of overlapping fields of view)."""
    from ..kernels import reference

    C = len(rig)
    cams = [c.warp_camera() for c in rig.cameras]
    frac = np.eye(C)
    for a in range(C):
        spec = rig.cameras[a]
        rays = unproject_pixels(cams[a], grid_pixels(spec, stride).reshape(-1, 2))
        X_a = rays * depth / np.linalg.norm(rays, axis=1, keepdims=True)
        for b in range(C):
            if a == b:
                continue
            T_b_a = np.linalg.inv(rig.cameras[b].T_b_c) @ spec.T_b_c
            X_b = X_a @ T_b_a[:3, :3].T + T_b_a[:3, 3]
            cam_b = cams[b]
            with np.errstate(all="ignore"):
                ok = reference.in_domain(cam_b, X_b)
                p = reference.project(cam_b, np.where(ok[:, None], X_b, [0.0, 0.0, 1.0]))
            inside = ok & (p[:, 0] >= 0) & (p[:, 0] <= cam_b.width - 1) & (p[:, 1] >= 0) & (p[:, 1] <= cam_b.height - 1)
            frac[a, b] = inside.mean()
    return frac


def unproject_pixels(cam, uv: np.ndarray) -> np.ndarray:
    """Unit-depth rays [M,3] (float64) of pixels ``uv`` [M,2] with the Warp camera model."""
    import warp as wp

    from ..kernels.ba import unproject_points_kernel

    out = wp.zeros(len(uv), dtype=wp.vec3, device="cpu")
    uv32 = wp.array(np.ascontiguousarray(uv, dtype=np.float32), dtype=wp.vec2, device="cpu")
    wp.launch(unproject_points_kernel, dim=len(uv), inputs=[cam, uv32], outputs=[out], device="cpu")
    return out.numpy().astype(np.float64)


def build_edges(
    keyframes,
    n_cameras: int,
    overlap: np.ndarray | None = None,
    radius: int = 2,
    cross_view: bool = True,
    cross_time: bool = False,
    min_overlap: float = 0.05,
) -> np.ndarray:
    """Edges [E,5] ``(i, ci, j, cj, kind)`` among ``keyframes`` (indices into the buffer).

    ``overlap`` [C,C] from :func:`camera_overlap` decides which camera pairs are linked
    (default: none across cameras)."""
    kfs = list(keyframes)
    pairs = []
    if overlap is not None:
        pairs = [(a, b) for a in range(n_cameras) for b in range(n_cameras) if a != b and overlap[a, b] >= min_overlap]
    edges = []
    for ai, i in enumerate(kfs):
        for aj, j in enumerate(kfs):
            if i == j or abs(ai - aj) > radius:
                continue
            for c in range(n_cameras):
                edges.append((i, c, j, c, TEMPORAL))
            if cross_time:
                edges.extend((i, a, j, b, CROSS_TIME) for a, b in pairs)
        if cross_view:
            edges.extend((i, a, i, b, CROSS_VIEW) for a, b in pairs)
    return np.array(edges, dtype=np.int32).reshape(-1, 5)


def sliding_window(n_keyframes: int, size: int) -> list[int]:
    """The last ``size`` keyframes (the online loop's MCBA window); its first is the gauge."""
    return list(range(max(0, n_keyframes - size), n_keyframes))
