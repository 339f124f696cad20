"""Dense depth refinement once poses are known: PatchMatch-style propagation and
multi-view geometric consistency.

:func:`propagate_depth` reuses the idea with per-pixel hypotheses instead of planes: once
poses are known, a dense depth map is improved by one PatchMatch-style pass (Bleyer et al.,
BMVC 2011; Galliani et al., ICCV 2015): every pixel tries its neighbours' depths and small
changes of its own (:func:`candidate_warp_kernel`), scored by the sweep's ZNCC over a window
sliding down each column (:func:`~.sweep.zncc_cost_kernel`), and keeps the best
(:func:`candidate_select_kernel`); at depth edges the best few are re-scored with
colour-adaptive support weights (:func:`rescore_pick_kernel`, :func:`support_weights_kernel`, :func:`adaptive_window_kernel`,
:func:`rescore_select_kernel`; Yoon & Kweon, PAMI 2006). :func:`consistent_depth` then keeps only the depths that
other views' depth maps confirm (geometric consistency, as multi-view stereo fusion does:
Schönberger et al., ECCV 2016; Yao et al., ECCV 2018), :func:`depth_agreement_kernel`.

Costs are the sweep's (:mod:`.sweep`: ZNCC over a window, ``NO_COST`` without information).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .camera import EQUIRECTANGULAR, FAR, NEAR, Camera, camera_in_domain, camera_project
from .sweep import NO_COST, keep_two_lowest, nearest_pixel, sample_bilinear, zncc_cost, zncc_cost_kernel

wp.set_module_options({"enable_backward": False})


@wp.func
def candidate_depth(depth: wp.array(dtype=float, ndim=2), cand: wp.vec3, y: int, x: int):
    """Depth (m) candidate ``cand = (dx, dy, factor)`` proposes for pixel (x, y): ``factor``
    times the depth ``(dx, dy)`` away, clamped to the image (0 = none there)."""
    H = depth.shape[0]
    W = depth.shape[1]
    return depth[wp.clamp(y + int(cand[1]), 0, H - 1), wp.clamp(x + int(cand[0]), 0, W - 1)] * cand[2]


@wp.kernel
def candidate_warp_kernel(
    ref_rays: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] unit-depth rays of the reference
    depth: wp.array(dtype=float, ndim=2),  # [H,W] current depth of the reference (m, 0 = none)
    candidates: wp.array(dtype=wp.vec3),  # [D] (dx, dy, factor)
    src: wp.array(dtype=float, ndim=3),  # [S,Hs,Ws] grey source images
    src_cams: wp.array(dtype=Camera),  # [S]
    T_src_ref: wp.array(dtype=wp.mat44),  # [S]
    s: int,  # the source of this launch
    row0: int,
    warped: wp.array(dtype=float, ndim=3),  # [D,H,W]
):
    """Grey value of source ``s`` where each reference pixel lands with candidate ``k``'s
    depth: ``factor * depth`` of the pixel ``(dx, dy)`` away (neighbour propagation and
    perturbation, as in PatchMatch stereo); ``-1`` outside."""
    k, r, x = wp.tid()
    y = r + row0
    c = candidates[k]
    z = candidate_depth(depth, c, y, x)
    value = float(-1.0)
    if z > 0.0:
        X = wp.transform_point(T_src_ref[s], ref_rays[y, x] * z)
        cam = src_cams[s]
        if camera_in_domain(cam, X, NEAR, FAR):
            uv = camera_project(cam, X)
            value = sample_bilinear(src, s, uv[0], uv[1], cam.width, cam.height)
    warped[k, y, x] = value


@wp.kernel
def candidate_select_kernel(
    m1: wp.array(dtype=float, ndim=3),  # [D,H,W]
    m2: wp.array(dtype=float, ndim=3),
    best_k: int,
    depth: wp.array(dtype=float, ndim=2),  # [H,W] m
    candidates: wp.array(dtype=wp.vec3),  # [D], candidate 0 = (0, 0, 1): the pixel's own depth
    out: wp.array(dtype=float, ndim=2),  # [H,W] m
):
    """Per pixel with a depth: the candidate of lowest cost (``best_k`` 1: the best source's;
    2: the mean of the two best, a candidate only one source sees counting the other as
    ``NO_COST``), replacing the current depth only when strictly better, and only where some
    source measured the current depth at all (next to a hole, or where it leaves every
    source, a neighbour's depth would otherwise win at any cost)."""
    y, x = wp.tid()
    value = depth[y, x]
    if value > 0.0 and m1[0, y, x] < NO_COST:
        best = float(NO_COST)
        for k in range(candidates.shape[0]):
            c = m1[k, y, x]
            if best_k > 1:
                c = 0.5 * (c + m2[k, y, x])  # a candidate only one source confirms pays for it
            cand = candidates[k]
            z = candidate_depth(depth, cand, y, x)
            if z > 0.0:
                if c < best:
                    best = c
                    value = z
    out[y, x] = value


@wp.kernel
def rescore_pick_kernel(
    m1: wp.array(dtype=float, ndim=3),  # [D,H,W] from window_zncc_kernel
    m2: wp.array(dtype=float, ndim=3),
    depth: wp.array(dtype=float, ndim=2),  # [H,W] m
    candidates: wp.array(dtype=wp.vec3),  # [D]
    at_edge: wp.array(dtype=wp.int32, ndim=2),  # [H,W] 1 where the depth window straddles an edge
    best_k: int,  # 1 or 2, as in candidate_select_kernel
    picked: wp.array(dtype=wp.int32, ndim=3),  # [K,H,W] candidate indices, -1 = none
):
    """Per pixel at a depth edge whose own depth some source measured: its own depth
    (candidate 0) and the ``K - 1`` other candidates of lowest plain-window cost (as
    :func:`candidate_select_kernel` ranks them, so the plain winner is among them), to be
    re-scored by :func:`adaptive_window_kernel`."""
    y, x = wp.tid()
    K = picked.shape[0]
    for j in range(K):
        picked[j, y, x] = -1
    if at_edge[y, x] == 0 or depth[y, x] <= 0.0 or m1[0, y, x] >= NO_COST:
        return
    picked[0, y, x] = 0
    for j in range(1, K):
        best = float(NO_COST)
        bk = int(-1)
        for k in range(1, candidates.shape[0]):
            cand = candidates[k]
            z = candidate_depth(depth, cand, y, x)
            c = m1[k, y, x]
            if best_k > 1:
                c = 0.5 * (c + m2[k, y, x])
            taken = int(0)
            for i in range(1, j):
                if picked[i, y, x] == k:
                    taken = 1
            if z > 0.0 and taken == 0 and c < best:
                best = c
                bk = k
        picked[j, y, x] = bk


@wp.kernel
def support_weights_kernel(
    ref: wp.array(dtype=float, ndim=2),  # [H,W] grey reference
    colour: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] RGB reference in [0,1]
    radius: int,
    gamma_colour: float,  # L1 RGB difference at which a window pixel's weight falls by e
    gamma_distance: float,  # px, likewise for its distance from the centre
    at: wp.array(dtype=wp.int32, ndim=2),  # [H,W] 1 where weights are wanted
    weights: wp.array(dtype=float, ndim=3),  # [H,W,(2r+1)^2] row-major window; 0 outside the image
    moments: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] weighted (sum w, sum w a, sum w a^2) over the window
):
    """Adaptive support weights (Yoon & Kweon, PAMI 2006) of each wanted pixel's window: its
    colour likeness to the centre and its distance, so that at a depth edge the surface the
    centre belongs to decides, not the one across the edge (the fattening of plain windows).
    They depend on the reference alone: computed once, they serve every candidate and source
    of :func:`adaptive_window_kernel`, and so do the reference's weighted moments."""
    y, x = wp.tid()
    if at[y, x] == 0:
        return
    H = ref.shape[0]
    W = ref.shape[1]
    centre = colour[y, x]
    t = float(0.0)
    sa = float(0.0)
    saa = float(0.0)
    o = int(0)
    for dy in range(-radius, radius + 1):
        yy = y + dy
        for dx in range(-radius, radius + 1):
            xx = x + dx
            w = float(0.0)
            if yy >= 0 and yy < H and xx >= 0 and xx < W:
                d = colour[yy, xx] - centre
                w = wp.exp(-(wp.abs(d[0]) + wp.abs(d[1]) + wp.abs(d[2])) / gamma_colour - wp.sqrt(float(dx * dx + dy * dy)) / gamma_distance)
                a = ref[yy, xx]
                t += w
                sa += w * a
                saa += w * a * a
            weights[y, x, o] = w
            o += 1
    moments[y, x] = wp.vec3(t, sa, saa)


@wp.func
def lagrange3(t: float):
    """Quadratic Lagrange weights of the nodes at -1, 0, 1 for ``t`` in [-1, 1]."""
    return wp.vec3(0.5 * t * (t - 1.0), 1.0 - t * t, 0.5 * t * (t + 1.0))


@wp.kernel
def adaptive_window_kernel(
    ref: wp.array(dtype=float, ndim=2),  # [H,W] grey reference
    weights: wp.array(dtype=float, ndim=3),  # [H,W,(2r+1)^2] from support_weights_kernel
    moments: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] from support_weights_kernel
    ref_rays: wp.array(dtype=wp.vec3, ndim=2),  # [H,W]
    depth: wp.array(dtype=float, ndim=2),  # [H,W] m
    candidates: wp.array(dtype=wp.vec3),  # [D]
    picked: wp.array(dtype=wp.int32, ndim=3),  # [K,H,W] from rescore_pick_kernel
    src: wp.array(dtype=float, ndim=3),  # [S,Hs,Ws] grey sources
    src_cams: wp.array(dtype=Camera),  # [S]
    T_src_ref: wp.array(dtype=wp.mat44),  # [S]
    s: int,  # the source of this launch
    radius: int,
    min_std: float,
    row0: int,
    a1: wp.array(dtype=float, ndim=3),  # [K,H,W] lowest cost over the sources so far
    a2: wp.array(dtype=float, ndim=3),  # [K,H,W] second lowest
):
    """``1 - ZNCC`` of a picked candidate with adaptive support weights: the whole window at
    the candidate's depth (placed in the source through 3x3 projected nodes, a biquadratic
    map: 9 projections instead of (2r+1)^2), each pixel weighted as :func:`support_weights_kernel` says;
    ``NO_COST`` once samples outside the source carry more than 0.1 % of the window's weight
    (the moments then count the valid samples only)."""
    j, r, x = wp.tid()
    y = r + row0
    k = picked[j, y, x]
    if k < 0:
        return
    cand = candidates[k]
    z = candidate_depth(depth, cand, y, x)
    cam = src_cams[s]
    T = T_src_ref[s]
    # Off the equirectangular model and the image's rim the window's samples follow the
    # biquadratic map through 3x3 exactly projected nodes (the window's corners, edge
    # midpoints and centre; rays at one depth): 9 projections per window, not (2r+1)^2.
    H = ref_rays.shape[0]
    W = ref_rays.shape[1]
    nodes = cam.model != EQUIRECTANGULAR and y >= radius and y + radius < H and x >= radius and x + radius < W
    Pu = wp.mat33(0.0)
    Pv = wp.mat33(0.0)
    if nodes:
        for ny in range(3):
            for nx in range(3):
                X = wp.transform_point(T, ref_rays[y + (ny - 1) * radius, x + (nx - 1) * radius] * z)
                if camera_in_domain(cam, X, NEAR, FAR):
                    uv = camera_project(cam, X)
                    Pu[ny, nx] = uv[0]
                    Pv[ny, nx] = uv[1]
                else:
                    nodes = False  # a node leaves the model's domain: every sample projected
    m = moments[y, x]
    t = m[0]
    n = t  # weight of the valid samples: the window's less what falls outside the source
    sa = m[1]
    saa = m[2]
    sb = float(0.0)
    sbb = float(0.0)
    sab = float(0.0)
    o = int(0)
    for dy in range(-radius, radius + 1):
        yy = y + dy
        ly = lagrange3(float(dy) / float(radius))
        qu = wp.vec3(0.0)
        qv = wp.vec3(0.0)
        if nodes:  # the row's nodes: Lagrange weights over the node rows
            for nx in range(3):
                qu[nx] = ly[0] * Pu[0, nx] + ly[1] * Pu[1, nx] + ly[2] * Pu[2, nx]
                qv[nx] = ly[0] * Pv[0, nx] + ly[1] * Pv[1, nx] + ly[2] * Pv[2, nx]
        for dx in range(-radius, radius + 1):
            xx = x + dx
            w = weights[y, x, o]
            o += 1
            if w > 0.0 and n >= 0.999 * t:
                b = float(-1.0)
                if nodes:
                    lx = lagrange3(float(dx) / float(radius))
                    b = sample_bilinear(src, s, wp.dot(lx, qu), wp.dot(lx, qv), cam.width, cam.height)
                else:
                    X = wp.transform_point(T, ref_rays[yy, xx] * z)
                    if camera_in_domain(cam, X, NEAR, FAR):
                        uv = camera_project(cam, X)
                        b = sample_bilinear(src, s, uv[0], uv[1], cam.width, cam.height)
                a = ref[yy, xx]
                if b >= 0.0:
                    sb += w * b
                    sbb += w * b * b
                    sab += w * a * b
                else:
                    n -= w
                    sa -= w * a
                    saa -= w * a * a
    c = float(NO_COST)
    if n >= 0.999 * t and n > 0.0:
        c = zncc_cost(n, sa, saa, sb, sbb, sab, min_std)
    keep_two_lowest(c, a1, a2, j, y, x)


@wp.kernel
def rescore_select_kernel(
    a1: wp.array(dtype=float, ndim=3),  # [K,H,W]
    a2: wp.array(dtype=float, ndim=3),
    picked: wp.array(dtype=wp.int32, ndim=3),  # [K,H,W]
    depth: wp.array(dtype=float, ndim=2),  # [H,W] m
    candidates: wp.array(dtype=wp.vec3),  # [D]
    best_k: int,  # 1 or 2, as in candidate_select_kernel
    out: wp.array(dtype=float, ndim=2),  # [H,W] m: overwritten where re-scored
):
    """Where the own depth was re-scored at all: the picked candidate of lowest adaptive
    cost (``best_k`` as in :func:`candidate_select_kernel`), replacing the plain-window pass's
    choice."""
    y, x = wp.tid()
    if picked[0, y, x] < 0 or a1[0, y, x] >= NO_COST:
        return
    best = float(NO_COST)
    value = depth[y, x]
    for j in range(picked.shape[0]):
        k = picked[j, y, x]
        if k >= 0:
            c = a1[j, y, x]
            if best_k > 1:
                c = 0.5 * (c + a2[j, y, x])
            cand = candidates[k]
            z = candidate_depth(depth, cand, y, x)
            if z > 0.0 and c < best:
                best = c
                value = z
    out[y, x] = value


# --------------------------------------------------------------------------------------
# Host-side stages.


def depth_candidates(steps=(8, 16), factors=(0.95, 0.98, 1.02, 1.05)) -> np.ndarray:
    """[D,3] candidates ``(dx, dy, factor)`` of :func:`propagate_depth`: the pixel's own
    depth first, the depths of the 8 pixels ``step`` away around it (axes and diagonals)
    for each of ``steps`` (px), and its own depth times each of ``factors``. (All 24 pixels
    of a 5x5 pattern 8 px apart did no better than these 16 on the built-in sequence.)"""
    own = [(0.0, 0.0, 1.0)]
    around = [(float(dx * s), float(dy * s), 1.0) for s in steps for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dx or dy]
    return np.array(own + around + [(0.0, 0.0, float(f)) for f in factors], np.float32)


def propagate_depth(
    ref_image: np.ndarray,
    ref_rays: wp.array,
    depth: np.ndarray,
    src_images,
    src_cams,
    T_src_ref: np.ndarray,
    candidates: np.ndarray | None = None,
    radius: int = 4,
    min_std: float = 0.005,
    best_k: int = 2,
    ref_colour: np.ndarray | None = None,
    rescore: int = 4,
    edge_ratio: float = 1.2,
    gamma_colour: float = 0.1,
    gamma_distance: float = 4.5,
    device=None,
) -> np.ndarray:
    """One PatchMatch-style pass over a dense depth map [H,W] (m, 0 = none) of a reference
    view with known poses: each pixel takes, among its own depth, its neighbours' depths
    and small perturbations (:func:`depth_candidates`), the one whose ``(2r+1)^2`` ZNCC
    against the sources is best (``best_k`` 1 or 2: the best source, or the mean of the two
    best: occlusion-robust; see :func:`candidate_select_kernel`). Runs on ``ref_rays``'s
    device unless ``device`` says otherwise.
    Depth edges move to where the images put them and plain surfaces take the
    photo-consistent value among nearby estimates; nothing is invented where no depth is.
    With ``ref_colour`` (RGB [H,W,3] in [0,1]), pixels whose window straddles a depth edge
    (depths spanning more than ``edge_ratio``) re-score their own depth and the
    ``rescore - 1`` best other candidates with colour-adaptive support weights
    (:func:`adaptive_window_kernel`), against the foreground fattening of plain windows.
    ``ref_image`` [H,W] grey in [0,1]; ``ref_rays`` [H,W] from :func:`camera_rays`;
    ``src_images``: S grey images; ``src_cams``: S :class:`Camera`; ``T_src_ref`` [S,4,4]."""
    from .launch import run_row_bands

    device = ref_rays.device if device is None else wp.get_device(device)
    H, W = depth.shape
    S = len(src_images)
    if S == 0:
        return np.asarray(depth, np.float32).copy()
    cand = depth_candidates() if candidates is None else np.asarray(candidates, np.float32)
    D = len(cand)
    Hs = max(im.shape[0] for im in src_images)
    Ws = max(im.shape[1] for im in src_images)
    src = np.zeros((S, Hs, Ws), np.float32)
    for s, im in enumerate(src_images):
        src[s, : im.shape[0], : im.shape[1]] = im
    src_w = wp.array(src, dtype=float, device=device)
    ref_w = wp.array(np.ascontiguousarray(ref_image, dtype=np.float32), dtype=float, device=device)
    depth_w = wp.array(np.ascontiguousarray(depth, dtype=np.float32), dtype=float, device=device)
    cand_w = wp.array(cand, dtype=wp.vec3, device=device)
    cams_w = wp.array(list(src_cams), dtype=Camera, device=device)
    T_w = wp.array(np.asarray(T_src_ref, np.float32).reshape(S, 4, 4), dtype=wp.mat44, device=device)
    # one source at a time: memory 3 x D x H x W floats, whatever the number of sources
    warped = wp.empty((D, H, W), dtype=float, device=device)
    m1 = wp.full((D, H, W), NO_COST, dtype=float, device=device)
    m2 = wp.full((D, H, W), NO_COST, dtype=float, device=device)
    for s in range(S):
        def warp_band(worker, row0, n, s=s):
            wp.launch(candidate_warp_kernel, dim=(D, n, W), inputs=[ref_rays, depth_w, cand_w, src_w, cams_w, T_w, s, row0], outputs=[warped], device=device)

        def zncc_band(worker, row0, n):  # reads rows above and below: after the whole warp
            wp.launch(zncc_cost_kernel, dim=(D, W), inputs=[ref_w, warped, radius, min_std, 1.0, row0, n, 1], outputs=[m1, m2], device=device)

        run_row_bands(device, H, warp_band)
        run_row_bands(device, H, zncc_band)  # every in-image pixel of the window valid
    out = wp.empty((H, W), dtype=float, device=device)
    wp.launch(candidate_select_kernel, dim=(H, W), inputs=[m1, m2, best_k, depth_w, cand_w], outputs=[out], device=device)
    if ref_colour is not None and rescore > 0:
        import cv2

        if rescore < 2:
            raise ValueError(f"propagate_depth: rescore must be 0 (off) or at least 2 (the own depth and another candidate), got {rescore}")
        ref_colour = np.asarray(ref_colour)
        if ref_colour.shape[:2] != (H, W) or ref_colour.ndim != 3 or ref_colour.shape[2] != 3 or ref_colour.dtype.kind != "f":
            raise ValueError(f"propagate_depth: ref_colour must be a float RGB image [{H},{W},3] in [0,1] like the depth map, got {ref_colour.dtype} {ref_colour.shape}")

        # pixels whose own window straddles a depth edge (its depths span more than edge_ratio)
        box = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        d = np.asarray(depth, np.float32)
        lo, hi = cv2.erode(np.where(d > 0, d, np.float32(1e9)), box), cv2.dilate(d, box)
        at_edge = wp.array(((hi > edge_ratio * lo) & (d > 0)).astype(np.int32), dtype=wp.int32, device=device)
        picked = wp.empty((rescore, H, W), dtype=wp.int32, device=device)
        wp.launch(rescore_pick_kernel, dim=(H, W), inputs=[m1, m2, depth_w, cand_w, at_edge, best_k], outputs=[picked], device=device)
        colour_w = wp.array(np.ascontiguousarray(ref_colour, dtype=np.float32), dtype=wp.vec3, device=device)
        weights = wp.zeros((H, W, (2 * radius + 1) ** 2), dtype=float, device=device)
        moments = wp.zeros((H, W), dtype=wp.vec3, device=device)
        wp.launch(support_weights_kernel, dim=(H, W), inputs=[ref_w, colour_w, radius, gamma_colour, gamma_distance, at_edge], outputs=[weights, moments], device=device)
        a1 = wp.full((rescore, H, W), NO_COST, dtype=float, device=device)
        a2 = wp.full((rescore, H, W), NO_COST, dtype=float, device=device)
        for s in range(S):
            def adaptive_band(worker, row0, n, s=s):
                wp.launch(adaptive_window_kernel, dim=(rescore, n, W), inputs=[ref_w, weights, moments, ref_rays, depth_w, cand_w, picked, src_w, cams_w, T_w, s, radius, min_std, row0], outputs=[a1, a2], device=device)

            run_row_bands(device, H, adaptive_band)
        wp.launch(rescore_select_kernel, dim=(H, W), inputs=[a1, a2, picked, depth_w, cand_w, best_k], outputs=[out], device=device)
    return out.numpy()


@wp.kernel
def depth_agreement_kernel(
    ref_rays: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] unit-depth rays of the reference
    depth: wp.array(dtype=float, ndim=2),  # [H,W] reference depth (m, 0 = none)
    src_rays: wp.array(dtype=wp.vec3, ndim=2),  # [Hs,Ws] unit-depth rays of the source
    src_depth: wp.array(dtype=float, ndim=2),  # [Hs,Ws] source depth (m, 0 = none)
    src_cam: Camera,
    T_src_ref: wp.mat44,
    T_ref_src: wp.mat44,
    tol: float,
    count: wp.array(dtype=wp.int32, ndim=2),  # [H,W] += 1 where the source agrees
):
    """Does the source's depth map put the point where the reference's does? The reference
    pixel's point goes into the source, takes the source depth at the nearest pixel there,
    and comes back: it agrees when it lands within ``tol`` (relative) of the reference
    depth along the reference ray (``|X| / |ray|``: depth or range, whatever the model)."""
    y, x = wp.tid()
    d = depth[y, x]
    if d > 0.0:
        u, v, inside = nearest_pixel(src_cam, wp.transform_point(T_src_ref, ref_rays[y, x] * d))
        if inside == 1:
            d2 = src_depth[v, u]
            if d2 > 0.0:
                back = wp.transform_point(T_ref_src, src_rays[v, u] * d2)
                if wp.abs(wp.length(back) / wp.length(ref_rays[y, x]) - d) < tol * d:
                    count[y, x] = count[y, x] + 1


def consistent_depth(ref_rays: wp.array, depth: np.ndarray, src_rays, src_depths, src_cams, T_src_ref: np.ndarray, min_views: int = 2, tol: float = 0.05, device=None) -> np.ndarray:
    """``depth`` [H,W] (m, 0 = none) with 0 wherever fewer than ``min_views`` of the S
    sources (all S where there are fewer; none: ``depth`` as is) confirm it (:func:`depth_agreement_kernel`): depths no other view's map
    reproduces, such as outliers in front of a far wall or a foreground edge spread onto
    the background in one view only, are dropped rather than trusted. ``src_rays``: S
    [Hs,Ws] ray arrays (:func:`camera_rays`), ``src_depths``: S depth maps [Hs,Ws],
    ``src_cams``: S :class:`Camera`, ``T_src_ref`` [S,4,4] reference camera -> source."""
    device = ref_rays.device if device is None else wp.get_device(device)
    depth = np.asarray(depth, np.float32)
    T_src_ref = np.asarray(T_src_ref, np.float64).reshape(-1, 4, 4)
    S = len(src_depths)
    if not len(src_rays) == len(src_cams) == len(T_src_ref) == S:
        raise ValueError(f"consistent_depth: {len(src_rays)} ray arrays, {S} depth maps, {len(src_cams)} cameras and {len(T_src_ref)} poses: expected one of each per source")
    need = min(min_views, S)  # a view with fewer sources is judged by all it has; none: kept as is
    if need <= 0:
        return depth.copy()
    H, W = depth.shape
    depth_w = wp.array(np.ascontiguousarray(depth), dtype=float, device=device)
    count = wp.zeros((H, W), dtype=wp.int32, device=device)
    for rays_s, d_s, cam_s, T in zip(src_rays, src_depths, src_cams, T_src_ref):
        M, M_inv = (wp.mat44(*m.astype(np.float32).ravel()) for m in (T, np.linalg.inv(T)))
        d_w = wp.array(np.ascontiguousarray(d_s, dtype=np.float32), dtype=float, device=device)
        wp.launch(depth_agreement_kernel, dim=(H, W), inputs=[ref_rays, depth_w, rays_s, d_w, cam_s, M, M_inv, float(tol)], outputs=[count], device=device)
    return np.where(count.numpy() >= need, depth, 0.0).astype(np.float32)
