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

from dataclasses import dataclass

from pathlib import Path

import numpy as np

from ..buffer import KeyframeBuffer, grid_pixels
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


# ======================================================================================
# Edge choice by view overlap, loop closure, and the factor graph that owns the edges.
# ======================================================================================

LOOP = 3  # edge kind: a long-range (revisit) edge found by :func:`loop_candidates`


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
    from ..kernels import reference

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
        Xc = Xj[sel]
        with np.errstate(all="ignore"):
            ok = known[sel] & reference.in_domain(cam, Xc)
            p = reference.project(cam, np.where(ok[..., None], Xc, [0.0, 0.0, 1.0]))
        ok &= np.isfinite(p).all(-1) & (p[..., 0] >= 0) & (p[..., 0] <= cam.width - 1) & (p[..., 1] >= 0) & (p[..., 1] <= cam.height - 1)
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


def loop_candidates(buffer: KeyframeBuffer, keyframes=None, config: GraphConfig | None = None, exclude=(), poses=None) -> np.ndarray:
    """Revisit candidates [M,5] ``(i, ci, j, cj, LOOP)``, one direction (i later than j).

    Keyframe pairs more than ``config.loop_min_gap`` apart in the list ``keyframes`` (default:
    all) whose rig positions lie within ``config.loop_radius`` times the median spacing of
    consecutive keyframes; per camera pair, optical axes within ``config.loop_max_angle``
    degrees and reprojected overlap (current poses and depths) of at least
    ``config.loop_min_overlap`` both ways; at most ``config.loop_max_per_view`` partners per
    view of i (largest overlap first). Edges in ``exclude`` (keys ``(i, ci, j, cj)``) are skipped.
    Pose proximity only proposes: :func:`confirm_loops` decides with the images."""
    cfg = config or GraphConfig()
    T_w_b = buffer.get_poses() if poses is None else np.asarray(poses)
    kfs = np.array(list(range(len(T_w_b))) if keyframes is None else [int(k) for k in keyframes], dtype=np.int64)
    if len(kfs) < cfg.loop_min_gap + 2:
        return np.zeros((0, 5), np.int32)
    pos = T_w_b[kfs, :3, 3]
    spacing = float(np.median(np.linalg.norm(np.diff(pos, axis=0), axis=1)))
    radius = cfg.loop_radius * max(spacing, 1e-6)
    ai, aj = np.nonzero(np.linalg.norm(pos[:, None] - pos[None], axis=-1) < radius)
    keep = ai - aj > cfg.loop_min_gap
    ai, aj = ai[keep], aj[keep]
    if not len(ai):
        return np.zeros((0, 5), np.int32)
    axes = optical_axes(buffer, T_w_b)
    C = len(buffer.rig)
    cos_max = np.cos(np.radians(cfg.loop_max_angle))
    exclude = {tuple(int(v) for v in k[:4]) for k in exclude}
    cand = [
        (int(kfs[a]), ci, int(kfs[b]), cj)
        for a, b in zip(ai, aj)
        for ci in range(C)
        for cj in range(C)
        if axes[kfs[a], ci] @ axes[kfs[b], cj] >= cos_max and (int(kfs[a]), ci, int(kfs[b]), cj) not in exclude
    ]
    if not cand:
        return np.zeros((0, 5), np.int32)
    cand = np.array(cand, dtype=np.int64)
    ov, _ = view_overlap(buffer, np.concatenate([cand, cand[:, [2, 3, 0, 1]]]), poses=T_w_b, sample=cfg.sample)
    score = np.minimum(ov[: len(cand)], ov[len(cand) :])
    out, count = [], {}
    for n in np.argsort(-score, kind="stable"):
        key = (int(cand[n, 0]), int(cand[n, 1]))
        if score[n] < cfg.loop_min_overlap or count.get(key, 0) >= cfg.loop_max_per_view:
            continue
        count[key] = count.get(key, 0) + 1
        out.append((*cand[n], LOOP))
    return np.array(out, dtype=np.int32).reshape(-1, 5)


@dataclass
class LoopCheck:
    """The verdict on one loop candidate (both directions measured)."""

    edge: tuple  # (i, ci, j, cj)
    confident: float  # min over the two directions: fraction of predicted-visible pixels with weight >= 0.5
    residual_px: float  # max over the two directions: median |target - predicted|, full-resolution px
    cycle_px: float  # median round-trip error i -> j -> i through both directions' targets, full-res px
    accepted: bool


def _bilinear(field: np.ndarray, mask: np.ndarray, q: np.ndarray):
    """Sample ``field`` [h,w,k] at points ``q`` [N,2] (x, y); ``ok`` [N] where all four
    neighbours lie inside and are set in ``mask`` [h,w]."""
    h, w = mask.shape
    x0 = np.floor(q[:, 0]).astype(np.int64)
    y0 = np.floor(q[:, 1]).astype(np.int64)
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    x0, y0 = np.where(ok, x0, 0), np.where(ok, y0, 0)
    fx, fy = (q[:, 0] - x0)[:, None], (q[:, 1] - y0)[:, None]
    ok &= mask[y0, x0] & mask[y0, x0 + 1] & mask[y0 + 1, x0] & mask[y0 + 1, x0 + 1]
    val = field[y0, x0] * (1 - fx) * (1 - fy) + field[y0, x0 + 1] * fx * (1 - fy) + field[y0 + 1, x0] * (1 - fx) * fy + field[y0 + 1, x0 + 1] * fx * fy
    return val, ok


def confirm_loops(buffer: KeyframeBuffer, candidates: np.ndarray, provider, config: GraphConfig | None = None):
    """Check loop candidates [M,>=4] against the images; returns ``(edges [A,5], targets
    [A,h,w,2], weights [A,h,w], checks list[LoopCheck])`` with the accepted edges in both
    directions (kind LOOP).

    ``provider.correspondences(buffer, edges)`` (best :class:`GuidedDIS`: flow from the
    predicted reprojection) measures both directions; a provider with a ``photometric``
    method (GuidedDIS) is asked without it, and its factor is applied to the accepted edges. A candidate is accepted when, in both
    directions, at least ``config.loop_min_confident`` of the pixels predicted to be visible
    carry a confident match (weight >= 0.5); the median distance between the matches and the
    prediction stays below ``config.loop_max_residual_px`` (the drift the loop may correct;
    unrelated views give large, incoherent flow); and going i -> j by the forward matches
    and back by the backward ones returns, in the median, within ``config.loop_max_cycle_px``
    of the start (two independent flows agree)."""
    cfg = config or GraphConfig()
    cand = _as_edges(candidates)[:, :4].astype(np.int32)
    M, s = len(cand), buffer.stride
    empty = (np.zeros((0, 5), np.int32), np.zeros((0, buffer.h, buffer.w, 2), np.float32), np.zeros((0, buffer.h, buffer.w), np.float32), [])
    if M == 0:
        return empty
    both = np.concatenate([cand, cand[:, [2, 3, 0, 1]]])
    # the checks judge the geometry: a provider's photometric factor (GuidedDIS) is applied
    # to the accepted edges' weights afterwards
    photometric = getattr(provider, "photometric", None)
    photometric = photometric if callable(photometric) else None
    targets, weights = provider.correspondences(buffer, both, photometric=False) if photometric else provider.correspondences(buffer, both)
    pred, valid, _ = reproject(buffer, both)
    checks, keep = [], []
    for m in range(M):
        conf, res = [], []
        for e in (m, m + M):
            good = valid[e] & (weights[e] >= 0.5)
            conf.append(good.sum() / max(valid[e].sum(), 1))
            res.append(float(np.median(np.linalg.norm(targets[e][good] - pred[e][good], axis=-1))) * s if good.any() else np.inf)
        f, b = m, m + M
        good = valid[f] & (weights[f] >= 0.5)
        start = np.stack(np.nonzero(good)[::-1], -1).astype(np.float64)  # (x, y) grid pixels of view i
        back, ok = _bilinear(targets[b].astype(np.float64), weights[b] >= 0.5, targets[f][good].astype(np.float64))
        cycle = float(np.median(np.linalg.norm(back[ok] - start[ok], axis=-1))) * s if ok.sum() >= 10 else np.inf
        accepted = min(conf) >= cfg.loop_min_confident and max(res) <= cfg.loop_max_residual_px and cycle <= cfg.loop_max_cycle_px
        checks.append(LoopCheck(tuple(int(v) for v in cand[m]), float(min(conf)), float(max(res)), cycle, bool(accepted)))
        if accepted:
            keep += [f, b]
    if not keep:
        return empty[:3] + (checks,)
    edges = np.concatenate([both[keep], np.full((len(keep), 1), LOOP, np.int32)], 1)
    targets, weights = targets[keep], weights[keep]
    if photometric:
        targets, weights = photometric(buffer, both[keep], targets, weights)
    return edges, targets, weights, checks


class FactorGraph:
    """The MCBA edges of a keyframe buffer and their correspondences (in the spirit of
    DROID-SLAM's ``FactorGraph``).

    An edge is a key ``(i, ci, j, cj)`` with a kind (TEMPORAL, CROSS_VIEW, CROSS_TIME, LOOP).
    Every edge the graph knows is either *active* (part of the next MCBA problem,
    :meth:`arrays`) or *stored* (taken out of the problem, e.g. when it left the online
    window, with its correspondences kept for later reuse, as DROID keeps inactive edges
    for global BA). Correspondences per edge: ``targets`` [h,w,2] float32 (reduced-grid
    pixels of view (j, cj)) and ``weights`` [h,w] float32 in [0,1], as a
    :class:`~mcgs_warp.frontend.flow.FlowProvider` returns them; an edge may be active before
    they are computed (:meth:`missing`, :meth:`compute`). Keyframe indices are buffer
    indices; nothing renumbers them.

    ``rig_overlap`` [C,C] (:func:`camera_overlap`) links cameras for cross-view edges."""

    def __init__(self, buffer: KeyframeBuffer, rig_overlap: np.ndarray | None = None, config: GraphConfig | None = None):
        self.buf = buffer
        self.rig_overlap = rig_overlap
        self.cfg = config or GraphConfig()
        self._kind: dict = {}  # key -> kind, every known edge (insertion order)
        self._active: dict = {}  # key -> None: the active edges, in insertion order
        self._corr: dict = {}  # key -> (targets [h,w,2], weights [h,w])
        self._leaving: dict = {}  # keyframe i -> {key: None}: edges with correspondences leaving i
        self._saved: dict = {}  # key -> (segment, row): where the checkpoint store holds its current correspondences
        self._store: Path | None = None  # the folder _saved refers to
        self._seg_rows: dict = {}  # segment -> rows written to it

    # ---- membership --------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._active)

    def __contains__(self, key) -> bool:
        return tuple(int(v) for v in key[:4]) in self._active

    @property
    def edges(self) -> np.ndarray:
        """Active edges [E,5] int32 ``(i, ci, j, cj, kind)`` in the order they were added."""
        return self._rows(self._active)

    @property
    def stored(self) -> np.ndarray:
        """Edges [S,5] known but not active (their correspondences are kept)."""
        return self._rows(k for k in self._kind if k not in self._active)

    def _rows(self, keys) -> np.ndarray:
        return np.array([(*k, self._kind[k]) for k in keys], dtype=np.int32).reshape(-1, 5)

    @staticmethod
    def _keys(edges) -> list:
        return [tuple(int(v) for v in row[:4]) for row in _as_edges(edges)]

    def add(self, edges, targets=None, weights=None) -> np.ndarray:
        """Activate ``edges`` [E,4|5] (kind from column 4, else inferred: same keyframe ->
        cross-view, same camera -> temporal, otherwise cross-time). With ``targets``
        [E,h,w,2] and ``weights`` [E,h,w] their correspondences are stored too (replacing
        older ones); a stored edge comes back with its kept correspondences. Returns the
        edges [N,5] that were not active before."""
        e = _as_edges(edges)
        keys = self._keys(e)
        if targets is not None:
            self.set_correspondences(e, targets, weights)
        new = []
        for n, k in enumerate(keys):
            if k not in self._kind or e.shape[1] > 4:
                self._kind[k] = int(e[n, 4]) if e.shape[1] > 4 else _edge_kind(*k)
            if k not in self._active:
                self._active[k] = None
                new.append(k)
        return self._rows(new)

    def remove(self, edges=None, keyframes=None, outside=None, kinds=None, store: bool = True) -> np.ndarray:
        """Take active edges out of the problem: those in ``edges`` [E,>=4], touching a
        keyframe in ``keyframes``, or with an end outside the window ``outside`` (keyframes
        that stay), restricted to ``kinds`` if given. ``store`` keeps them (and their
        correspondences) for later reuse; ``store=False`` forgets them. Returns the removed
        edges [R,5]."""
        sel = set(self._active)
        if edges is not None:
            sel &= set(self._keys(edges))
        if keyframes is not None:
            ks = {int(k) for k in keyframes}
            sel = {k for k in sel if k[0] in ks or k[2] in ks}
        if outside is not None:
            win = {int(k) for k in outside}
            sel = {k for k in sel if k[0] not in win or k[2] not in win}
        if kinds is not None:
            sel = {k for k in sel if self._kind[k] in set(kinds)}
        gone = [k for k in self._active if k in sel]
        rows = self._rows(gone)
        for k in gone:
            del self._active[k]
            if not store:
                del self._kind[k]
                self._drop_corr(k)
        return rows

    def forget_keyframes(self, keyframes) -> int:
        """Drop every edge (active or stored) touching ``keyframes``, with its
        correspondences (the keyframes left the buffer or were re-initialized). Returns the count."""
        ks = {int(k) for k in keyframes}
        return self.forget(self._rows([k for k in self._kind if k[0] in ks or k[2] in ks]))

    # ---- correspondences ---------------------------------------------------------------
    def has_correspondences(self, key) -> bool:
        return tuple(int(v) for v in key[:4]) in self._corr

    def missing(self, edges=None) -> np.ndarray:
        """Edges [M,5] among ``edges`` (default: the active ones) without correspondences."""
        keys = list(self._active) if edges is None else self._keys(edges)
        return self._rows_known(k for k in dict.fromkeys(keys) if k not in self._corr)

    def set_correspondences(self, edges, targets, weights) -> None:
        """Store ``targets`` [E,h,w,2] and ``weights`` [E,h,w] for ``edges`` [E,>=4] (known
        edges keep their activity; unknown ones become stored edges)."""
        keys = self._keys(edges)
        t = np.asarray(targets, dtype=np.float32)
        w = np.asarray(weights, dtype=np.float32)
        shape = (len(keys), self.buf.h, self.buf.w)
        if t.shape != shape + (2,) or w.shape != shape:
            raise ValueError(f"targets/weights must be {shape + (2,)} / {shape}, got {t.shape} / {w.shape}")
        for n, k in enumerate(keys):
            self._kind.setdefault(k, _edge_kind(*k))
            self._corr[k] = (t[n].copy(), w[n].copy())
            self._leaving.setdefault(k[0], {})[k] = None
            self._saved.pop(k, None)  # changed: the next checkpoint writes it again

    def _drop_corr(self, key) -> None:
        if self._corr.pop(key, None) is not None:
            self._leaving[key[0]].pop(key, None)
            self._saved.pop(key, None)

    def measured_weight(self, keyframe: int, n_cameras: int) -> np.ndarray:
        """[C,h,w] float32: summed correspondence confidence of every edge (active or stored)
        leaving each grid pixel of ``keyframe`` (which of its pixels something measured).
        Indexed by source keyframe: the cost grows with that keyframe's edges, not the graph's."""
        out = np.zeros((n_cameras, self.buf.h, self.buf.w), np.float32)
        for k in self._leaving.get(int(keyframe), ()):
            out[k[1]] += self._corr[k][1]
        return out

    def correspondences(self, edges=None):
        """Stacked ``targets`` [E,h,w,2] and ``weights`` [E,h,w] of ``edges`` (default: the
        active ones); KeyError when some have none (see :meth:`missing`)."""
        keys = list(self._active) if edges is None else self._keys(edges)
        absent = [k for k in keys if k not in self._corr]
        if absent:
            raise KeyError(f"no correspondences for {len(absent)} edge(s), e.g. {absent[0]}; compute them first")
        if not keys:
            return np.zeros((0, self.buf.h, self.buf.w, 2), np.float32), np.zeros((0, self.buf.h, self.buf.w), np.float32)
        return np.stack([self._corr[k][0] for k in keys]), np.stack([self._corr[k][1] for k in keys])

    def compute(self, provider, edges=None) -> np.ndarray:
        """Compute and store correspondences with ``provider`` (``correspondences(buffer,
        edges [E,4] int32) -> (targets, weights)``) for ``edges`` [E,>=4], replacing any kept
        ones (default: the active edges that have none). Returns the edges computed [N,5]."""
        rows = self.missing() if edges is None else self._rows_of(edges)
        if len(rows):
            t, w = provider.correspondences(self.buf, np.ascontiguousarray(rows[:, :4], dtype=np.int32))
            self.set_correspondences(rows, t, w)
        return rows

    def _rows_of(self, edges) -> np.ndarray:
        return self._rows_known(dict.fromkeys(self._keys(edges)))

    def _rows_known(self, keys) -> np.ndarray:
        """Rows [N,5] of ``keys``, the kind inferred for edges the graph does not know (asking
        about an edge does not add it)."""
        return np.array([(*k, self._kind.get(k, _edge_kind(*k))) for k in keys], dtype=np.int32).reshape(-1, 5)

    def forget(self, edges) -> int:
        """Drop ``edges`` [E,>=4] (active or stored) with their correspondences; returns the count."""
        gone = [k for k in self._keys(edges) if k in self._kind]
        for k in gone:
            self._active.pop(k, None)
            self._drop_corr(k)
            del self._kind[k]
        return len(gone)

    def refresh(self, provider, keyframes, kinds=(TEMPORAL, CROSS_TIME, LOOP)) -> np.ndarray:
        """Recompute with ``provider`` (e.g. :class:`GuidedDIS`, from the current geometry) the
        correspondences of the active edges of ``kinds`` touching ``keyframes``; cross-view
        edges are left alone by default (their rig geometry does not change), and so are edges
        the provider calls settled (``provider.settled(buffer, edges, targets, weights)``, if it
        has one: the current geometry already predicts their matches). Returns the edges
        recomputed [R,5]."""
        ks = {int(k) for k in keyframes}
        kinds = set(kinds)
        keys = [k for k in self._active if (k[0] in ks or k[2] in ks) and self._kind[k] in kinds]
        if keys and hasattr(provider, "settled"):  # edges the geometry already explains keep their matches
            known = [k for k in keys if k in self._corr]
            if known:
                t, w = self.correspondences(self._rows(known))
                settled = {k for k, done in zip(known, provider.settled(self.buf, self._rows(known), t, w)) if done}
                keys = [k for k in keys if k not in settled]
        return self.compute(provider, self._rows(keys)) if keys else np.zeros((0, 5), np.int32)

    def items(self):
        """Every edge with correspondences, active or stored: ``(edge [5] int32, targets
        [h,w,2], weights [h,w])`` (e.g. to see which pixels of a keyframe are measured)."""
        for k, (t, w) in self._corr.items():
            yield np.array((*k, self._kind[k]), np.int32), t, w

    def arrays(self, keyframes=None):
        """The MCBA problem: active ``edges`` [E,5] int32 (restricted to those with both ends
        in ``keyframes`` if given), ``targets`` [E,h,w,2] and ``weights`` [E,h,w] float32."""
        keys = list(self._active)
        if keyframes is not None:
            ks = {int(k) for k in keyframes}
            keys = [k for k in keys if k[0] in ks and k[2] in ks]
        edges = self._rows(keys)
        t, w = self.correspondences(edges)
        return edges, t, w

    # ---- edge choice -------------------------------------------------------------------
    def update_window(self, keyframes, cross_view: bool = True, cross_time: bool = False, max_gap: int | None = None) -> np.ndarray:
        """Make the active set the overlap-chosen edges among ``keyframes``
        (:func:`overlap_edges`, current geometry): active edges outside the window or no
        longer chosen are stored (loop edges inside the window stay); chosen ones are
        activated (with kept correspondences where known). Returns the edges [N,5] still
        without correspondences, for the caller to :meth:`compute` with its providers."""
        chosen = overlap_edges(self.buf, keyframes, self.rig_overlap, self.cfg, cross_view=cross_view, cross_time=cross_time, max_gap=max_gap)
        keep = set(self._keys(chosen))
        win = {int(k) for k in keyframes}
        drop = [k for k in self._active if not (k in keep or (self._kind[k] == LOOP and k[0] in win and k[2] in win))]
        self.remove(np.array(drop, dtype=np.int32).reshape(-1, 4))
        self.add(chosen)
        return self.missing()

    def close_loops(self, provider, keyframes=None) -> list:
        """Find revisits among ``keyframes`` (default: all) by pose proximity and overlap
        (:func:`loop_candidates`, skipping edges the graph already knows), confirm them with
        ``provider`` (:func:`confirm_loops`) and activate the accepted ones, both directions,
        with their correspondences. Returns the :class:`LoopCheck` of every candidate."""
        cand = loop_candidates(self.buf, keyframes, self.cfg, exclude=self._kind)
        edges, t, w, checks = confirm_loops(self.buf, cand, provider, self.cfg)
        if len(edges):
            self.add(edges, t, w)
        return checks

    # ---- checkpoints -------------------------------------------------------------------
    def state_arrays(self, store=None) -> dict:
        """Plain arrays for a checkpoint (``np.savez``): ``graph_edges`` [N,5] int32 (every
        known edge), ``graph_active`` [N] bool, ``graph_has_corr`` [N] bool, and the
        correspondences of the edges that have them, in order: inline as ``graph_targets``
        [M,h,w,2] / ``graph_weights`` [M,h,w] float32, or, with a ``store`` folder, as
        ``graph_segment`` / ``graph_row`` [M] int64 into segment files ``store/seg_<n>.npz``.
        A segment is written once, holding the correspondences that changed since the last
        call (not every edge every time) and the live rows of segments that had fallen below
        half live, so the folder stays within about twice the live data once
        :meth:`prune_store` has removed the segments nothing refers to any more."""
        keys = list(self._kind)
        corr = [k for k in keys if k in self._corr]
        h, w = self.buf.h, self.buf.w
        out = {
            "graph_edges": self._rows(keys),
            "graph_active": np.array([k in self._active for k in keys], bool),
            "graph_has_corr": np.array([k in self._corr for k in keys], bool),
        }
        if store is None:
            out["graph_targets"] = np.array([self._corr[k][0] for k in corr], np.float32).reshape(-1, h, w, 2)
            out["graph_weights"] = np.array([self._corr[k][1] for k in corr], np.float32).reshape(-1, h, w)
            return out
        from ..io import atomic_write

        if self._store != Path(store):  # another folder: it holds none of ours
            self._saved, self._store, self._seg_rows = {}, Path(store), {}
        fresh = [k for k in corr if k not in self._saved]
        if fresh:  # also move the live rows of segments now less than half live (they get pruned)
            live: dict = {}
            for sg, _ in self._saved.values():
                live[sg] = live.get(sg, 0) + 1
            sparse = {sg for sg, n in self._seg_rows.items() if live.get(sg, 0) < 0.5 * n}
            fresh += [k for k in corr if k in self._saved and self._saved[k][0] in sparse]
            seg = 1 + max(_segments(store), default=-1)  # above every file there (ours among them)
            with atomic_write(Path(store) / f"seg_{seg:06d}.npz", "wb") as f:
                np.savez(f, targets=np.array([self._corr[k][0] for k in fresh], np.float32), weights=np.array([self._corr[k][1] for k in fresh], np.float32))
            self._saved.update({k: (seg, n) for n, k in enumerate(fresh)})
            self._seg_rows[seg] = len(fresh)
        out["graph_segment"] = np.array([self._saved[k][0] for k in corr], np.int64)
        out["graph_row"] = np.array([self._saved[k][1] for k in corr], np.int64)
        return out

    def prune_store(self, store) -> int:
        """Delete the segment files of ``store`` that no edge's current correspondences are
        in (call after the checkpoint that stopped referring to them is in place). Returns the count."""
        used = {s for s, _ in self._saved.values()}
        gone = [n for n in _segments(store) if n not in used]
        for n in gone:
            self._seg_rows.pop(n, None)
            (Path(store) / f"seg_{n:06d}.npz").unlink(missing_ok=True)
        return len(gone)

    def load_state_arrays(self, arrays, store=None) -> None:
        """Restore the state written by :meth:`state_arrays` (replacing the current one);
        ``store``: the segment folder it was written with, if any."""
        e = np.asarray(arrays["graph_edges"]).reshape(-1, 5)
        active = np.asarray(arrays["graph_active"], bool)
        has = np.asarray(arrays["graph_has_corr"], bool)
        saved, seg_rows = {}, {}
        if "graph_segment" in arrays:
            if store is None:
                raise ValueError("the checkpoint keeps its correspondences in segment files: pass their folder")
            seg, row = np.asarray(arrays["graph_segment"]), np.asarray(arrays["graph_row"])
            if len(seg) != has.sum() or len(row) != has.sum():
                raise ValueError("inconsistent factor-graph arrays in the checkpoint")
            t = np.zeros((len(seg), self.buf.h, self.buf.w, 2), np.float32)
            w = np.zeros((len(seg), self.buf.h, self.buf.w), np.float32)
            for n in np.unique(seg):
                with np.load(Path(store) / f"seg_{int(n):06d}.npz") as z:
                    sel = seg == n
                    t[sel], w[sel] = z["targets"][row[sel]], z["weights"][row[sel]]
                    seg_rows[int(n)] = len(z["weights"])
            saved = {tuple(int(v) for v in r[:4]): (int(a), int(b)) for r, a, b in zip(e[has], seg, row)}
        else:
            t, w = np.asarray(arrays["graph_targets"]), np.asarray(arrays["graph_weights"])
        if len(active) != len(e) or len(has) != len(e) or len(t) != has.sum() or len(w) != has.sum():
            raise ValueError("inconsistent factor-graph arrays in the checkpoint")
        self._kind = {tuple(int(v) for v in row[:4]): int(row[4]) for row in e}
        self._active = {tuple(int(v) for v in row[:4]): None for row, a in zip(e, active) if a}
        self._corr, self._leaving, self._saved = {}, {}, {}  # set_correspondences fills the first two
        if has.any():
            self.set_correspondences(e[has], t, w)
        self._saved, self._store = saved, (Path(store) if saved else None)
        self._seg_rows = seg_rows

def _segments(store) -> list:
    """Segment numbers of the files ``seg_<n>.npz`` in ``store`` (none if it does not exist)."""
    folder = Path(store)
    return sorted(int(p.stem[4:]) for p in folder.glob("seg_*.npz")) if folder.is_dir() else []
