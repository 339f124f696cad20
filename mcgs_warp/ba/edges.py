"""MCBA edges: which (keyframe, camera) views are linked by correspondences, and by how much
their views overlap.

An edge ``(i, ci, j, cj)`` predicts pixels of view (i, ci) in view (j, cj) through the
single formula ``T_cj_ci = inv(T_b_cj) inv(T_w_bj) T_w_bi T_b_ci`` (DESIGN.md):

* temporal edges: same camera, keyframes up to ``radius`` apart (paper eq. 7);
* cross-view edges: same keyframe, cameras whose fields of view overlap (eq. 8;
  the rig pose cancels, the known baseline fixes the metric scale);
* cross-camera-and-time edges (optional): overlapping cameras at nearby keyframes;
* loop edges: revisits found and confirmed by :mod:`mcgs_warp.ba.loops`.

Edges come in both directions, so every view's depth is constrained by its neighbours. The
online and global edge choice is by reprojected view overlap (:func:`overlap_edges`); the
:class:`~mcgs_warp.ba.graph.FactorGraph` owns the chosen edges and their correspondences.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..buffer import KeyframeBuffer, grid_pixels
from ..rig import Rig

TEMPORAL, CROSS_VIEW, CROSS_TIME = 0, 1, 2


def camera_overlap(rig: Rig, depth: float = 5.0, stride: int = 8) -> np.ndarray:
    """Fraction [C,C] of camera a's pixels that camera b sees when the scene lies at
    ``depth`` metres (a rough, rig-only test of overlapping fields of view)."""
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
            p, ok, _ = project_points(cam_b, X_b)
            inside = ok & (p[:, 0] >= 0) & (p[:, 0] <= cam_b.width - 1) & (p[:, 1] >= 0) & (p[:, 1] <= cam_b.height - 1)
            frac[a, b] = inside.mean()
    return frac


def project_points(cam, X: np.ndarray, jacobian: bool = False, near: float | None = None, far: float | None = None):
    """Pixels [...,2] (float64, 0 where not ok), whether each point projects (finite, between
    the near and far planes, inside the model's domain) [...] and, with ``jacobian``, the
    analytic ``d uv / d X`` [...,2,3] (else None) of camera-frame points ``X`` [...,3] (m) in
    Warp camera ``cam``: the kernels' own camera model, on the CPU (host-side callers)."""
    import warp as wp

    from ..kernels.ba import project_points_kernel
    from ..kernels.camera import FAR, NEAR, mat23

    X = np.asarray(X, dtype=np.float64)
    shape = X.shape[:-1]
    M = int(np.prod(shape))
    uv = wp.zeros(M, dtype=wp.vec2, device="cpu")
    J = wp.zeros(M, dtype=mat23, device="cpu")
    ok = wp.zeros(M, dtype=wp.int32, device="cpu")
    if M:
        pts = wp.array(np.ascontiguousarray(X.reshape(M, 3), dtype=np.float32), dtype=wp.vec3, device="cpu")
        wp.launch(project_points_kernel, dim=M, inputs=[cam, pts, NEAR if near is None else near, FAR if far is None else far], outputs=[uv, J, ok], device="cpu")
    return (
        uv.numpy().astype(np.float64).reshape(*shape, 2),
        ok.numpy().astype(bool).reshape(shape),
        J.numpy().astype(np.float64).reshape(*shape, 2, 3) if jacobian else None,
    )


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


LOOP = 3  # edge kind: a long-range (revisit) edge found by :func:`mcgs_warp.ba.loops.loop_candidates`


@dataclass
class GraphConfig:
    """Edge-selection and loop-closure settings (the values the tests and the system use)."""

    min_overlap: float = 0.3  # a temporal/cross-time pair needs this reprojected overlap, both ways
    max_angle: float = 90.0  # deg between optical axes of a temporal/cross-time pair (opposite views
    #   of the same floor overlap geometrically, but no flow matches them)
    max_per_view: int = 4  # temporal (+ cross-time) partners per view, nearest in index first (radius 2 had 4)
    sample: int = 2  # overlap is measured on every ``sample``-th grid pixel (rows and columns)
    min_camera_overlap: float = 0.05  # rig overlap (camera_overlap) that links two cameras
    loop_min_gap: int = 8  # keyframes: loop partners lie further apart in index than this (> the window)
    loop_radius: float = 2.0  # rig positions closer than this times the median keyframe spacing
    loop_max_angle: float = 45.0  # deg between the two views' optical axes
    loop_min_overlap: float = 0.3  # reprojected overlap of a loop candidate, both ways
    loop_max_per_view: int = 2  # loop partners per view (largest overlap first)
    loop_min_confident: float = 0.3  # fraction of predicted-visible pixels the flow confirms (weight >= 0.5)
    loop_max_residual_px: float = 24.0  # full-res px: median |flow target - predicted| (the drift it may correct)
    loop_max_cycle_px: float = 3.0  # full-res px: median round-trip error i -> j -> i of the two directions


def _as_edges(edges) -> np.ndarray:
    """``edges`` (array or list of rows ``(i, ci, j, cj[, kind])``) as an int64 array [E,4|5]."""
    e = np.asarray(edges, dtype=np.int64)
    if e.size == 0:
        return np.zeros((0, 4), np.int64)
    if e.ndim != 2 or e.shape[1] < 4:
        raise ValueError(f"edges must be [E,4] or [E,5] (i, ci, j, cj[, kind]), got shape {e.shape}")
    return e


def _edge_kind(i: int, ci: int, j: int, cj: int) -> int:
    """The kind of an edge given without one: same keyframe -> cross-view, same camera ->
    temporal, otherwise cross-time."""
    return CROSS_VIEW if i == j else TEMPORAL if ci == cj else CROSS_TIME


def reproject(buffer: KeyframeBuffer, edges: np.ndarray, poses: np.ndarray | None = None, disp: np.ndarray | None = None, sample: int = 1):
    """Where the grid pixels of view (i, ci) land in view (j, cj) at the current geometry.

    ``edges`` [E,>=4] ``(i, ci, j, cj)``; ``poses`` [K,4,4] ``T_w_b`` (default: the buffer's)
    and ``disp`` [K,C,h,w] inverse depth (1/m, 0 = unknown; default: the buffer's). Only every
    ``sample``-th grid row and column is used. Returns

    * ``uv`` [E,hs,ws,2] float64: reduced-grid pixel coordinates in view (j, cj) (0 where invalid);
    * ``valid`` [E,hs,ws] bool: the pixel has depth, lands in front of camera cj (its model's
      domain, beyond the near plane) and inside its image;
    * ``known`` [E,hs,ws] bool: the pixel of view (i, ci) has depth (inside camera ci's grid).

    Through ``T_cj_ci = inv(T_b_cj) inv(T_w_bj) T_w_bi T_b_ci`` (DESIGN.md), vectorized in NumPy."""
    e = np.asarray(edges)[:, :4].astype(np.int64)
    E, s = len(e), int(sample)
    T_w_b = buffer.get_poses() if poses is None else np.asarray(poses, dtype=np.float64)
    disp = buffer.disp.numpy() if disp is None else disp
    rays = buffer.rays.numpy()[:, ::s, ::s].astype(np.float64)  # [C,hs,ws,3] unit depth
    hs, ws = rays.shape[1:3]
    uv = np.zeros((E, hs, ws, 2))
    valid = np.zeros((E, hs, ws), bool)
    known = np.zeros((E, hs, ws), bool)
    if E == 0:
        return uv, valid, known
    T_b_c = np.stack([c.T_b_c for c in buffer.rig.cameras]).astype(np.float64)
    rows, cols = np.arange(0, buffer.h, s)[:, None], np.arange(0, buffer.w, s)[None, :]
    in_grid = np.stack([(rows < c.height) & (cols < c.width) for c in buffer.reduced])  # [C,hs,ws]
    i, ci, j, cj = e.T
    d = np.asarray(disp[i, ci, ::s, ::s], dtype=np.float64)
    known[:] = (d > 0) & in_grid[ci]
    z = np.where(known, 1.0 / np.where(known, d, 1.0), 0.0)
    T = np.linalg.inv(T_w_b[j] @ T_b_c[cj]) @ T_w_b[i] @ T_b_c[ci]  # [E,4,4] T_cj_ci
    X = rays[ci] * z[..., None]
    Xj = np.einsum("eab,ehwb->ehwa", T[:, :3, :3], X) + T[:, None, None, :3, 3]
    for c in np.unique(cj):
        sel = cj == c
        cam = buffer.reduced[c].warp_camera()
        p, ok, _ = project_points(cam, Xj[sel])
        ok &= known[sel] & (p[..., 0] >= 0) & (p[..., 0] <= cam.width - 1) & (p[..., 1] >= 0) & (p[..., 1] <= cam.height - 1)
        uv[sel] = np.where(ok[..., None], p, 0.0)
        valid[sel] = ok
    return uv, valid, known


def view_overlap(buffer: KeyframeBuffer, pairs: np.ndarray, poses=None, disp=None, sample: int = 2, chunk: int = 256):
    """Reprojected overlap of view (i, ci) in view (j, cj) for each row of ``pairs`` [P,>=4].

    Returns ``overlap`` [P] (fraction of the grid pixels of (i, ci) with depth that land in
    front of camera cj and inside its image; 0 without depth) and ``mean_flow`` [P] (mean
    displacement in reduced-grid pixels of those that land, the DROID-style motion measure;
    meaningful for same-camera pairs; inf where none land). Geometry as :func:`reproject`,
    in chunks of ``chunk`` pairs to bound memory."""
    pairs = _as_edges(pairs)
    P = len(pairs)
    overlap, flow = np.zeros(P), np.full(P, np.inf)
    T_w_b = buffer.get_poses() if poses is None else poses
    disp = buffer.disp.numpy() if disp is None else disp
    rows, cols = np.mgrid[0 : buffer.h : sample, 0 : buffer.w : sample]
    for a in range(0, P, chunk):
        uv, valid, known = reproject(buffer, pairs[a : a + chunk], T_w_b, disp, sample)
        n_known = known.sum((1, 2))
        n_valid = valid.sum((1, 2))
        overlap[a : a + chunk] = np.where(n_known > 0, n_valid / np.maximum(n_known, 1), 0.0)
        motion = np.hypot(uv[..., 0] - cols, uv[..., 1] - rows)
        with np.errstate(invalid="ignore", divide="ignore"):
            flow[a : a + chunk] = np.where(n_valid > 0, (motion * valid).sum((1, 2)) / n_valid, np.inf)
    return overlap, flow


def camera_pairs(overlap: np.ndarray | None, n_cameras: int, min_overlap: float = 0.05) -> list[tuple[int, int]]:
    """Ordered camera pairs (a, b), a != b, whose rig overlap [C,C] reaches ``min_overlap``."""
    if overlap is None:
        return []
    return [(a, b) for a in range(n_cameras) for b in range(n_cameras) if a != b and overlap[a, b] >= min_overlap]


def overlap_edges(
    buffer: KeyframeBuffer,
    keyframes,
    rig_overlap: np.ndarray | None = None,
    config: GraphConfig | None = None,
    cross_view: bool = True,
    cross_time: bool = False,
    max_gap: int | None = None,
    poses=None,
) -> np.ndarray:
    """Edges [E,5] ``(i, ci, j, cj, kind)`` among ``keyframes`` chosen by view overlap, not by
    index distance.

    Temporal (same camera) and, with ``cross_time``, cross-camera-and-time pairs (camera
    pairs linked by ``rig_overlap`` [C,C], or every pair without it) are candidates when their
    keyframes are at most ``max_gap`` apart in the list (default: any). A candidate is kept
    when its reprojected overlap (:func:`view_overlap`, current poses and depths) reaches
    ``config.min_overlap`` in both directions; candidates are taken nearest in index first
    (then largest overlap), at most ``config.max_per_view`` per view, and each kept pair adds
    both directions (so a view may end with one more partner than the bound when a later
    pair fills another's last slot). Cross-view edges (same keyframe) come from
    ``rig_overlap`` as in :func:`build_edges`."""
    cfg = config or GraphConfig()
    kfs = [int(k) for k in keyframes]
    C = len(buffer.rig)
    pairs_c = [(c, c) for c in range(C)]
    if cross_time:
        pairs_c += camera_pairs(rig_overlap, C, cfg.min_camera_overlap) if rig_overlap is not None else [(a, b) for a in range(C) for b in range(C) if a != b]
    cand = []
    for ai in range(len(kfs)):
        for aj in range(ai + 1, len(kfs)):
            if max_gap is not None and aj - ai > max_gap:
                continue
            cand.extend((kfs[ai], a, kfs[aj], b, aj - ai) for a, b in pairs_c)
    if cand:
        axes = optical_axes(buffer, poses)
        cos_max = np.cos(np.radians(cfg.max_angle))
        cand = [c for c in cand if axes[c[0], c[1]] @ axes[c[2], c[3]] >= cos_max]
    edges = []
    if cand:
        cand = np.array(cand, dtype=np.int64)
        both = np.concatenate([cand[:, :4], cand[:, [2, 3, 0, 1]]])
        ov, _ = view_overlap(buffer, both, poses=poses, sample=cfg.sample)
        score = np.minimum(ov[: len(cand)], ov[len(cand) :])
        order = np.lexsort((-score, cand[:, 4]))
        count: dict = {}
        for n in order:
            if score[n] < cfg.min_overlap:
                continue
            i, ci, j, cj, _ = (int(v) for v in cand[n])
            if count.get((i, ci), 0) >= cfg.max_per_view or count.get((j, cj), 0) >= cfg.max_per_view:
                continue
            count[(i, ci)] = count.get((i, ci), 0) + 1
            count[(j, cj)] = count.get((j, cj), 0) + 1
            kind = TEMPORAL if ci == cj else CROSS_TIME
            edges += [(i, ci, j, cj, kind), (j, cj, i, ci, kind)]
    if cross_view:
        for k in kfs:
            edges.extend((k, a, k, b, CROSS_VIEW) for a, b in camera_pairs(rig_overlap, C, cfg.min_camera_overlap))
    return np.array(edges, dtype=np.int32).reshape(-1, 5)


def optical_axes(buffer: KeyframeBuffer, poses=None) -> np.ndarray:
    """World directions [K,C,3] of every view's optical axis (camera +z)."""
    T_w_b = buffer.get_poses() if poses is None else np.asarray(poses)
    R_b_c = np.stack([c.T_b_c[:3, :3] for c in buffer.rig.cameras])
    return np.einsum("kab,cbd->kcad", T_w_b[:, :3, :3], R_b_c)[..., 2]
