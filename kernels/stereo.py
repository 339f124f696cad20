"""Sweep stereo for any mix of camera models, without rectification.

Plane sweeping needs only each camera's projection and unprojection (Häne et al.,
3DV 2014), so pinhole (+ radial-tangential), fisheye and equirectangular views can be
matched as they are. A reference view is swept through inverse-depth hypotheses
``rho_k``: reference pixel ``p`` with unit-depth ray ``ray(p)`` (``camera_unproject(cam,
p, 1)``) is lifted to ``X = ray(p) / rho_k``, moved into each source view by
``T_src_ref`` and sampled there. Because the unit-depth ray has ``z = 1`` for pinhole and
fisheye cameras and length 1 for equirectangular ones, ``rho`` is ``1/z`` or ``1/range``
(DESIGN.md's depth): fronto-parallel planes for the former, a sphere sweep (Meuleman et
al., CVPR 2021) for the latter, with one code path.

Stages (each one launch; the per-pixel ones take a ``row0`` so that CPU launches can
run in bands of rows on several threads, see :mod:`.launch`):

1. :func:`sweep_warp_kernel` ``[S,D,H,W]``: grey value of source ``s`` where hypothesis
   ``k`` of each reference pixel lands (``-1``: outside the source or its domain).
2. :func:`zncc_cost_kernel` ``[S,D,H,W]``: ``1 - ZNCC`` over a ``(2r+1)^2`` window
   between the reference and the warped source (ZNCC ignores gain and offset between
   cameras); ``NO_COST`` where fewer than 3/4 of the window is valid or the reference
   window is flat (std below ``min_std``: textureless, nothing to match).
3. :func:`aggregate_kernel` ``[D,H,W]``: per hypothesis, the mean of the best
   ``best_k`` source costs (occlusion-robust, PlaneSweepLib's BEST_K).
4. :func:`select_kernel` ``[H,W]``: winner-take-all, parabola fit over the three
   neighbouring hypotheses, and the confidence: zero unless the best cost is below
   ``max_cost`` and the uniqueness ratio (best / second best, the second taken outside
   +-1 hypothesis of the winner) is below ``max_ratio``, and unless the winner lies
   strictly inside the range; otherwise ``1 - best / max_cost``.
5. :func:`lr_check_kernel` ``[H,W]``: forward-backward consistency between the sweeps
   of two views (reference pixel -> other view -> back); errors above ``max_px`` zero
   the confidence (occlusions, mismatches).

:func:`propagate_depth` reuses the idea with per-pixel hypotheses instead of planes: once
poses are known, a dense depth map is improved by one PatchMatch-style pass (Bleyer et al.,
BMVC 2011; Galliani et al., ICCV 2015): every pixel tries its neighbours' depths and small
changes of its own (:func:`candidate_warp_kernel`), scored by ZNCC with separable window
sums (:func:`window_rows_kernel`, :func:`window_zncc_kernel`), and keeps the best
(:func:`candidate_select_kernel`); at depth edges the best few are re-scored with
colour-adaptive support weights (:func:`rescore_pick_kernel`, :func:`adaptive_window_kernel`,
:func:`rescore_select_kernel`; Yoon & Kweon, PAMI 2006). :func:`consistent_depth` then keeps only the depths that
other views' depth maps confirm (geometric consistency, as multi-view stereo fusion does:
Schönberger et al., ECCV 2016; Yao et al., ECCV 2018), :func:`depth_agreement_kernel`.

:func:`refine_points` refines the depth of a few reference pixels at full resolution
(per-pixel candidates along the epipolar curve, :func:`point_cost_kernel`): the rig's
cross-view matches at the MCBA grid pixels.

:func:`patch_sad` scores many matches between views at once (:func:`patch_sad_kernel`: the
mean-removed SAD of two 7 x 7 patches), the photometric confidence of the guided flow.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .camera import FAR, NEAR, Camera, camera_in_domain, camera_project
from .mapping import sample_grid

wp.set_module_options({"enable_backward": False})

#: Cost of a hypothesis without information (outside the source, flat window).
NO_COST = wp.constant(3.0)
vec6f = wp.types.vector(6, dtype=wp.float32)


@wp.func
def sample_bilinear(img: wp.array(dtype=float, ndim=3), s: int, u: float, v: float, width: int, height: int):
    """Bilinear sample of ``img[s]`` at continuous pixel ``(u, v)`` (OpenCV centres); -1 outside."""
    if u < 0.0 or v < 0.0 or u > float(width - 1) or v > float(height - 1):
        return -1.0
    return sample_grid(img, s, u, v, width, height)


@wp.kernel
def sweep_warp_kernel(
    ref_rays: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] unit-depth rays of the reference
    rho: wp.array(dtype=float),  # [D] inverse-depth hypotheses (1/m)
    src: wp.array(dtype=float, ndim=3),  # [S,Hs,Ws] grey source images
    src_cams: wp.array(dtype=Camera),  # [S]
    T_src_ref: wp.array(dtype=wp.mat44),  # [S] reference camera -> source camera
    row0: int,
    warped: wp.array(dtype=float, ndim=4),  # [S,D,H,W]
):
    s, k, r, x = wp.tid()
    y = r + row0
    X = wp.transform_point(T_src_ref[s], ref_rays[y, x] / rho[k])
    cam = src_cams[s]
    value = float(-1.0)
    if camera_in_domain(cam, X, NEAR, FAR):
        uv = camera_project(cam, X)
        value = sample_bilinear(src, s, uv[0], uv[1], cam.width, cam.height)
    warped[s, k, y, x] = value


@wp.func
def zncc_cost(n: float, sa: float, saa: float, sb: float, sbb: float, sab: float, min_std: float):
    """``1 - ZNCC`` from the sums of ``n`` sample pairs (a, b); ``NO_COST`` where the
    reference window is flat (std below ``min_std``) or the source's is (below half that)."""
    va = saa / n - (sa / n) * (sa / n)
    vb = sbb / n - (sb / n) * (sb / n)
    c = float(NO_COST)
    if va > min_std * min_std and vb > 0.25 * min_std * min_std:
        ncc = (sab / n - (sa / n) * (sb / n)) / wp.sqrt(va * vb)
        c = 1.0 - wp.clamp(ncc, -1.0, 1.0)
    return c


@wp.kernel
def zncc_cost_kernel(
    ref: wp.array(dtype=float, ndim=2),  # [H,W] grey reference
    warped: wp.array(dtype=float, ndim=4),  # [S,D,H,W]
    radius: int,
    min_std: float,
    row0: int,
    cost: wp.array(dtype=float, ndim=4),  # [S,D,H,W]: 1 - ZNCC, or NO_COST
):
    s, k, r, x = wp.tid()
    y = r + row0
    H = ref.shape[0]
    W = ref.shape[1]
    n = float(0.0)
    sa = float(0.0)
    sb = float(0.0)
    saa = float(0.0)
    sbb = float(0.0)
    sab = float(0.0)
    total = float(0.0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            yy = y + dy
            xx = x + dx
            if yy >= 0 and yy < H and xx >= 0 and xx < W:
                total += 1.0
                b = warped[s, k, yy, xx]
                if b >= 0.0:
                    a = ref[yy, xx]
                    n += 1.0
                    sa += a
                    sb += b
                    saa += a * a
                    sbb += b * b
                    sab += a * b
    c = float(NO_COST)
    if n >= 0.75 * total and n > 1.0:
        c = zncc_cost(n, sa, saa, sb, sbb, sab, min_std)
    cost[s, k, y, x] = c


@wp.kernel
def aggregate_kernel(cost: wp.array(dtype=float, ndim=4), best_k: int, agg: wp.array(dtype=float, ndim=3)):
    """Mean of the ``best_k`` (1 or 2) lowest source costs per hypothesis; NO_COST if none."""
    k, y, x = wp.tid()
    m1 = float(NO_COST)
    m2 = float(NO_COST)
    for s in range(cost.shape[0]):
        c = cost[s, k, y, x]
        if c < m1:
            m2 = m1
            m1 = c
        elif c < m2:
            m2 = c
    out = m1
    if best_k > 1 and m2 < NO_COST:
        out = 0.5 * (m1 + m2)
    agg[k, y, x] = out


@wp.kernel
def select_kernel(
    agg: wp.array(dtype=float, ndim=3),  # [D,H,W]
    rho: wp.array(dtype=float),  # [D], uniformly spaced
    max_cost: float,
    max_ratio: float,
    inv_depth: wp.array(dtype=float, ndim=2),  # [H,W] 1/m (0: none)
    best_cost: wp.array(dtype=float, ndim=2),
    confidence: wp.array(dtype=float, ndim=2),  # [H,W] in [0,1]
):
    y, x = wp.tid()
    D = agg.shape[0]
    kb = int(0)
    c1 = float(NO_COST)
    for k in range(D):
        c = agg[k, y, x]
        if c < c1:
            c1 = c
            kb = k
    c2 = float(NO_COST)
    for k in range(D):
        if k < kb - 1 or k > kb + 1:
            c2 = wp.min(c2, agg[k, y, x])
    conf = float(0.0)
    value = float(0.0)
    if c1 < max_cost and kb > 0 and kb < D - 1:
        cm = agg[kb - 1, y, x]
        cp = agg[kb + 1, y, x]
        offset = float(0.0)
        curv = cm - 2.0 * c1 + cp
        if cm < NO_COST and cp < NO_COST and curv > 1.0e-9:
            offset = wp.clamp(0.5 * (cm - cp) / curv, -0.5, 0.5)
        value = rho[kb] + offset * (rho[1] - rho[0])
        if c1 < max_ratio * c2 and value > 0.0:
            conf = 1.0 - c1 / max_cost
    inv_depth[y, x] = value
    best_cost[y, x] = c1
    confidence[y, x] = conf


@wp.func
def nearest_pixel(cam: Camera, X: wp.vec3):
    """``(u, v, inside)``: the pixel nearest to where ``X`` (camera frame, m) projects, and
    1 if ``X`` is in the camera's domain and that pixel in its image (else 0)."""
    u = int(-1)
    v = int(-1)
    inside = int(0)
    if camera_in_domain(cam, X, NEAR, FAR):
        uv = camera_project(cam, X)
        u = int(wp.round(uv[0]))
        v = int(wp.round(uv[1]))
        if u >= 0 and v >= 0 and u < cam.width and v < cam.height:
            inside = 1
    return u, v, inside


@wp.kernel
def lr_check_kernel(
    rays_a: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] of view a
    inv_depth_a: wp.array(dtype=float, ndim=2),
    cam_b: Camera,
    rays_b: wp.array(dtype=wp.vec3, ndim=2),  # [Hb,Wb] of view b
    inv_depth_b: wp.array(dtype=float, ndim=2),
    cam_a: Camera,
    T_b_a: wp.mat44,
    T_a_b: wp.mat44,
    max_px: float,
    confidence_a: wp.array(dtype=float, ndim=2),  # zeroed where inconsistent
):
    y, x = wp.tid()
    ra = inv_depth_a[y, x]
    if ra <= 0.0:
        confidence_a[y, x] = 0.0
        return
    ub, vb, inside = nearest_pixel(cam_b, wp.transform_point(T_b_a, rays_a[y, x] / ra))
    err = float(1.0e9)
    if inside == 1:
        rb = inv_depth_b[vb, ub]
        if rb > 0.0:
            Xa = wp.transform_point(T_a_b, rays_b[vb, ub] / rb)
            if camera_in_domain(cam_a, Xa, NEAR, FAR):
                pa = camera_project(cam_a, Xa)
                err = wp.length(pa - wp.vec2(float(x), float(y)))
    if err > max_px:
        confidence_a[y, x] = 0.0


@wp.func
def candidate_depth(depth: wp.array(dtype=float, ndim=2), cand: wp.vec3, y: int, x: int):
    """Depth (m) candidate ``cand = (dx, dy, factor)`` proposes for pixel (x, y): ``factor``
    times the depth ``(dx, dy)`` away, clamped to the image (0 = none there)."""
    H = depth.shape[0]
    W = depth.shape[1]
    return depth[wp.clamp(y + int(cand[1]), 0, H - 1), wp.clamp(x + int(cand[0]), 0, W - 1)] * cand[2]


@wp.func
def keep_two_lowest(c: float, m1: wp.array(dtype=float, ndim=3), m2: wp.array(dtype=float, ndim=3), k: int, y: int, x: int):
    """Fold one source's cost ``c`` into the lowest (``m1``) and second lowest (``m2``)."""
    a = m1[k, y, x]
    if c < a:
        m2[k, y, x] = a
        m1[k, y, x] = c
    elif c < m2[k, y, x]:
        m2[k, y, x] = c


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


#: Window sums of the propagation's ZNCC: in-image count, valid count, a, a^2, b, b^2, ab.
window_sums = wp.types.vector(length=7, dtype=float)


@wp.kernel
def window_rows_kernel(
    ref: wp.array(dtype=float, ndim=2),  # [H,W] grey reference
    warped: wp.array(dtype=float, ndim=3),  # [D,H,W] one source
    radius: int,
    row0: int,
    rows: wp.array(dtype=window_sums, ndim=3),  # [D,H,W]
):
    """Horizontal ``2r+1`` sums per pixel of :data:`window_sums` (a: reference, b: warped
    source; the moments over valid samples only). First pass of a separable window sum:
    the ZNCC of :func:`window_zncc_kernel` then costs O(r) per pixel, not O(r^2)."""
    k, r, x = wp.tid()
    y = r + row0
    W = ref.shape[1]
    t = float(0.0)
    n = float(0.0)
    sa = float(0.0)
    saa = float(0.0)
    sb = float(0.0)
    sbb = float(0.0)
    sab = float(0.0)
    for dx in range(-radius, radius + 1):
        xx = x + dx
        if xx >= 0 and xx < W:
            t += 1.0
            b = warped[k, y, xx]
            if b >= 0.0:
                a = ref[y, xx]
                n += 1.0
                sa += a
                saa += a * a
                sb += b
                sbb += b * b
                sab += a * b
    rows[k, y, x] = window_sums(t, n, sa, saa, sb, sbb, sab)


@wp.kernel
def window_zncc_kernel(
    rows: wp.array(dtype=window_sums, ndim=3),  # [D,H,W] from window_rows_kernel
    radius: int,
    min_std: float,
    row0: int,
    m1: wp.array(dtype=float, ndim=3),  # [D,H,W] lowest cost over the sources so far
    m2: wp.array(dtype=float, ndim=3),  # [D,H,W] second lowest
):
    """Second pass: vertical sums, ``1 - ZNCC`` of the window (``NO_COST`` unless every
    in-image pixel of the window is valid and both windows have texture), folded into the
    two lowest costs per candidate (sources come one launch at a time)."""
    k, r, x = wp.tid()
    y = r + row0
    H = rows.shape[1]
    t = float(0.0)  # scalar sums: vector accumulators made these loops 1.5-4x slower on the CPU
    n = float(0.0)
    sa = float(0.0)
    saa = float(0.0)
    sb = float(0.0)
    sbb = float(0.0)
    sab = float(0.0)
    for dy in range(-radius, radius + 1):
        yy = y + dy
        if yy >= 0 and yy < H:
            v = rows[k, yy, x]
            t += v[0]
            n += v[1]
            sa += v[2]
            saa += v[3]
            sb += v[4]
            sbb += v[5]
            sab += v[6]
    c = float(NO_COST)
    if n >= t and n > 1.0:
        c = zncc_cost(n, sa, saa, sb, sbb, sab, min_std)
    keep_two_lowest(c, m1, m2, k, y, x)


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
    (candidate 0) and the ``K - 1`` other candidates of lowest separable cost (as
    :func:`candidate_select_kernel` ranks them, so the separable winner is among them), to be
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
def adaptive_window_kernel(
    ref: wp.array(dtype=float, ndim=2),  # [H,W] grey reference
    colour: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] RGB reference in [0,1]: the support weights
    ref_rays: wp.array(dtype=wp.vec3, ndim=2),  # [H,W]
    depth: wp.array(dtype=float, ndim=2),  # [H,W] m
    candidates: wp.array(dtype=wp.vec3),  # [D]
    picked: wp.array(dtype=wp.int32, ndim=3),  # [K,H,W] from rescore_pick_kernel
    src: wp.array(dtype=float, ndim=3),  # [S,Hs,Ws] grey sources
    src_cams: wp.array(dtype=Camera),  # [S]
    T_src_ref: wp.array(dtype=wp.mat44),  # [S]
    s: int,  # the source of this launch
    radius: int,
    gamma_colour: float,  # L1 RGB difference at which a window pixel's weight falls by e
    gamma_distance: float,  # px, likewise for its distance from the centre
    min_std: float,
    row0: int,
    a1: wp.array(dtype=float, ndim=3),  # [K,H,W] lowest cost over the sources so far
    a2: wp.array(dtype=float, ndim=3),  # [K,H,W] second lowest
):
    """``1 - ZNCC`` of a picked candidate with adaptive support weights (Yoon & Kweon, PAMI
    2006): the whole window at the candidate's depth, each pixel weighted by its colour
    likeness to the centre and its distance, so that at a depth edge the surface the centre
    belongs to decides, not the one across the edge (the fattening of plain windows)."""
    j, r, x = wp.tid()
    y = r + row0
    k = picked[j, y, x]
    if k < 0:
        return
    H = depth.shape[0]
    W = depth.shape[1]
    cand = candidates[k]
    z = candidate_depth(depth, cand, y, x)
    cam = src_cams[s]
    T = T_src_ref[s]
    centre = colour[y, x]
    t = float(0.0)  # weight of the in-image window, then of its valid samples and their moments
    n = float(0.0)
    sa = float(0.0)
    saa = float(0.0)
    sb = float(0.0)
    sbb = float(0.0)
    sab = float(0.0)
    for dy in range(-radius, radius + 1):
        yy = y + dy
        for dx in range(-radius, radius + 1):
            xx = x + dx
            if yy >= 0 and yy < H and xx >= 0 and xx < W:
                d = colour[yy, xx] - centre
                w = wp.exp(-(wp.abs(d[0]) + wp.abs(d[1]) + wp.abs(d[2])) / gamma_colour - wp.sqrt(float(dx * dx + dy * dy)) / gamma_distance)
                t += w
                X = wp.transform_point(T, ref_rays[yy, xx] * z)
                if camera_in_domain(cam, X, NEAR, FAR):
                    uv = camera_project(cam, X)
                    b = sample_bilinear(src, s, uv[0], uv[1], cam.width, cam.height)
                    if b >= 0.0:
                        a = ref[yy, xx]
                        n += w
                        sa += w * a
                        saa += w * a * a
                        sb += w * b
                        sbb += w * b * b
                        sab += w * a * b
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
    cost (``best_k`` as in :func:`candidate_select_kernel`), replacing the separable pass's
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


class SweepResult:
    """Inverse depth [H,W] (1/m, 0 = none), best cost and confidence [H,W] of a reference view."""

    def __init__(self, inv_depth, best_cost, confidence):
        self.inv_depth, self.best_cost, self.confidence = inv_depth, best_cost, confidence

    def depth(self) -> np.ndarray:
        """Depth [H,W] (m) where confident, else 0."""
        r, c = self.inv_depth.numpy(), self.confidence.numpy()
        return np.where((r > 0) & (c > 0), 1.0 / np.maximum(r, 1e-12), 0.0).astype(np.float32)


def camera_rays(cam: Camera, device) -> wp.array:
    """Unit-depth rays [H,W] (vec3) of every pixel of ``cam``."""
    from .ba import grid_rays_kernel

    cams = wp.array([cam], dtype=Camera, device=device)
    rays = wp.zeros((1, cam.height, cam.width), dtype=wp.vec3, device=device)
    wp.launch(grid_rays_kernel, dim=(1, cam.height, cam.width), inputs=[cams], outputs=[rays], device=device)
    return rays.reshape((cam.height, cam.width))


def inverse_depth_hypotheses(near: float, far: float, count: int) -> np.ndarray:
    """``count`` inverse depths uniform between 1/far and 1/near (1/m)."""
    return np.linspace(1.0 / far, 1.0 / near, count).astype(np.float32)


def sweep(
    ref_image: np.ndarray,
    ref_rays: wp.array,
    src_images,
    src_cams,
    T_src_ref: np.ndarray,
    rho: np.ndarray,
    radius: int = 2,
    min_std: float = 0.02,
    best_k: int = 1,
    max_cost: float = 0.5,
    max_ratio: float = 0.9,
    device=None,
) -> SweepResult:
    """Sweep the reference view through ``rho`` [D] against ``S`` sources.

    ``ref_image`` [H,W] grey float in [0,1]; ``ref_rays`` from :func:`camera_rays`;
    ``src_images``: S grey images; ``src_cams``: S :class:`Camera`; ``T_src_ref``
    [S,4,4] reference camera -> source camera (m)."""
    from .launch import run_row_bands

    device = wp.get_device(device)
    H, W = ref_image.shape
    S, D = len(src_images), len(rho)
    Hs = max(im.shape[0] for im in src_images)
    Ws = max(im.shape[1] for im in src_images)
    src = np.zeros((S, Hs, Ws), np.float32)
    for s, im in enumerate(src_images):
        src[s, : im.shape[0], : im.shape[1]] = im
    src_w = wp.array(src, dtype=float, device=device)
    ref_w = wp.array(np.ascontiguousarray(ref_image, dtype=np.float32), dtype=float, device=device)
    rho_w = wp.array(np.asarray(rho, np.float32), dtype=float, device=device)
    cams_w = wp.array(list(src_cams), dtype=Camera, device=device)
    T_w = wp.array(np.asarray(T_src_ref, np.float32).reshape(S, 4, 4), dtype=wp.mat44, device=device)
    warped = wp.empty((S, D, H, W), dtype=float, device=device)
    cost = wp.empty((S, D, H, W), dtype=float, device=device)

    def warp_band(worker, row0, rows):
        wp.launch(sweep_warp_kernel, dim=(S, D, rows, W), inputs=[ref_rays, rho_w, src_w, cams_w, T_w, row0], outputs=[warped], device=device)

    def cost_band(worker, row0, rows):
        wp.launch(zncc_cost_kernel, dim=(S, D, rows, W), inputs=[ref_w, warped, radius, min_std, row0], outputs=[cost], device=device)

    run_row_bands(device, H, warp_band)
    run_row_bands(device, H, cost_band)
    agg = wp.empty((D, H, W), dtype=float, device=device)
    wp.launch(aggregate_kernel, dim=(D, H, W), inputs=[cost, best_k], outputs=[agg], device=device)
    inv_depth = wp.empty((H, W), dtype=float, device=device)
    best = wp.empty((H, W), dtype=float, device=device)
    conf = wp.empty((H, W), dtype=float, device=device)
    wp.launch(select_kernel, dim=(H, W), inputs=[agg, rho_w, max_cost, max_ratio], outputs=[inv_depth, best, conf], device=device)
    return SweepResult(inv_depth, best, conf)


def left_right_check(a: SweepResult, rays_a, cam_a: Camera, b: SweepResult, rays_b, cam_b: Camera, T_b_a: np.ndarray, max_px: float = 1.0, device=None) -> None:
    """Zero ``a``'s confidence where going a -> b (with a's depth) -> a (with b's depth)
    misses the start pixel by more than ``max_px`` (in a's pixels)."""
    device = wp.get_device(device)
    T_b_a = np.asarray(T_b_a, np.float64)
    M_ba, M_ab = (wp.mat44(*m.astype(np.float32).ravel()) for m in (T_b_a, np.linalg.inv(T_b_a)))
    H, W = a.inv_depth.shape
    wp.launch(lr_check_kernel, dim=(H, W), inputs=[rays_a, a.inv_depth, cam_b, rays_b, b.inv_depth, cam_a, M_ba, M_ab, max_px], outputs=[a.confidence], device=device)


@wp.func
def sample_replicated(img: wp.array(dtype=float, ndim=3), v: int, u: float, y: float, width: int, height: int):
    """Bilinear sample of ``img[v]`` at ``(u, y)`` with the border replicated (as OpenCV's
    ``BORDER_REPLICATE``: the coordinates are clamped into the image); a NaN coordinate reads
    as 0."""
    if wp.isnan(u):
        u = 0.0
    if wp.isnan(y):
        y = 0.0
    return sample_grid(img, v, wp.clamp(u, 0.0, float(width - 1)), wp.clamp(y, 0.0, float(height - 1)), width, height)


#: The largest patch :func:`patch_sad_kernel` holds: radius 3, 7 x 7 differences.
PATCH_MAX_RADIUS = 3
patch_diffs = wp.types.vector(length=(2 * PATCH_MAX_RADIUS + 1) ** 2, dtype=float)


@wp.kernel
def patch_sad_kernel(
    grey: wp.array(dtype=float, ndim=3),  # [V,H,W] grey views, zero-padded to the largest
    sizes: wp.array(dtype=wp.vec2i),  # [V] (width, height) of each view
    view_a: wp.array(dtype=wp.int32),  # [E]
    view_b: wp.array(dtype=wp.int32),  # [E]
    uv_a: wp.array(dtype=wp.vec2, ndim=3),  # [E,h,w] full-resolution pixels in view_a
    uv_b: wp.array(dtype=wp.vec2, ndim=3),  # [E,h,w] their matches in view_b
    radius: int,  # at most PATCH_MAX_RADIUS
    e0: int,  # first match row (edge) of this launch
    sad: wp.array(dtype=float, ndim=3),  # [E,h,w] out
):
    """Mean absolute difference of the two ``(2r+1)^2`` patches, their mean difference
    removed (a brightness offset between the views does not count)."""
    eb, y, x = wp.tid()
    e = eb + e0
    va = view_a[e]
    vb = view_b[e]
    pa = uv_a[e, y, x]
    pb = uv_b[e, y, x]
    wa = sizes[va][0]
    ha = sizes[va][1]
    wb = sizes[vb][0]
    hb = sizes[vb][1]
    d = patch_diffs()
    k = int(0)
    mean = float(0.0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            a = sample_replicated(grey, va, pa[0] + float(dx), pa[1] + float(dy), wa, ha)
            b = sample_replicated(grey, vb, pb[0] + float(dx), pb[1] + float(dy), wb, hb)
            d[k] = a - b
            mean += a - b
            k += 1
    mean = mean / float(k)
    total = float(0.0)
    for m in range(k):
        total += wp.abs(d[m] - mean)
    sad[e, y, x] = total / float(k)


def patch_sad(views, view_a, view_b, uv_a: np.ndarray, uv_b: np.ndarray, radius: int = 3, device=None) -> np.ndarray:
    """Mean-removed patch SAD [E,h,w] of many matches in one launch: ``views`` a list of
    grey images [H,W] (float, any sizes); match ``(e, y, x)`` compares view ``view_a[e]``
    around full-resolution pixel ``uv_a[e,y,x]`` with view ``view_b[e]`` around
    ``uv_b[e,y,x]`` (bilinear, border replicated; ``uv`` [E,h,w,2] in px)."""
    device = wp.get_device(device)
    uv_a, uv_b = np.asarray(uv_a, np.float32), np.asarray(uv_b, np.float32)
    E = len(view_a)
    if uv_a.shape != uv_b.shape or uv_a.ndim != 4 or uv_a.shape[0] != E or uv_a.shape[3] != 2 or len(view_b) != E:
        raise ValueError(f"patch_sad: uv_a and uv_b must both be [E,h,w,2] with E = {E} pairs, got {uv_a.shape} and {uv_b.shape} ({len(view_b)} view_b)")
    if not 0 <= radius <= PATCH_MAX_RADIUS:
        raise ValueError(f"patch_sad: radius must be 0..{PATCH_MAX_RADIUS}, got {radius}")
    if E == 0:
        return np.zeros(uv_a.shape[:3], np.float32)
    for name, idx in (("view_a", view_a), ("view_b", view_b)):
        idx = np.asarray(idx)
        if idx.min() < 0 or idx.max() >= len(views):
            raise ValueError(f"patch_sad: {name} must index the {len(views)} views, got values {idx.min()}..{idx.max()}")
    H = max(v.shape[0] for v in views)
    W = max(v.shape[1] for v in views)
    grey = np.zeros((len(views), H, W), np.float32)
    for k, v in enumerate(views):
        grey[k, : v.shape[0], : v.shape[1]] = v
    sizes = np.array([(v.shape[1], v.shape[0]) for v in views], np.int32)
    from .launch import run_row_bands

    out = wp.empty(uv_a.shape[:3], dtype=float, device=device)
    inputs = [
        wp.array(grey, dtype=float, device=device),
        wp.array(sizes, dtype=wp.vec2i, device=device),
        wp.array(np.asarray(view_a, np.int32), dtype=wp.int32, device=device),
        wp.array(np.asarray(view_b, np.int32), dtype=wp.int32, device=device),
        wp.array(uv_a, dtype=wp.vec2, device=device),
        wp.array(uv_b, dtype=wp.vec2, device=device),
        int(radius),
    ]

    def band(worker, e0, n):  # on the CPU, bands of edges on all cores
        wp.launch(patch_sad_kernel, dim=(n,) + uv_a.shape[1:3], inputs=inputs + [e0], outputs=[out], device=device)

    run_row_bands(device, E, band)
    return out.numpy()


@wp.kernel
def reproject_kernel(
    rays: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] unit-depth rays of view i
    inv_depth: wp.array(dtype=float, ndim=2),  # [H,W] 1/m of view i (0: unknown)
    T_j_i: wp.mat44,  # view i camera -> view j camera
    cam_j: Camera,
    uv_j: wp.array(dtype=wp.vec2, ndim=2),  # [H,W] pixel of view j, or (-1e4, -1e4)
):
    """Where each pixel of view i lands in view j given its depth: the flow a geometry
    prediction implies (correspondences that follow the current depths and poses)."""
    y, x = wp.tid()
    out = wp.vec2(-1.0e4, -1.0e4)
    r = inv_depth[y, x]
    if r > 0.0:
        X = wp.transform_point(T_j_i, rays[y, x] / r)
        if camera_in_domain(cam_j, X, NEAR, FAR):
            out = camera_project(cam_j, X)
    uv_j[y, x] = out


def reproject(rays, inv_depth: np.ndarray, T_j_i: np.ndarray, cam_j: Camera, device=None) -> np.ndarray:
    """Pixels [H,W,2] of view j seen at each pixel of view i (``rays`` [H,W] of view i,
    ``inv_depth`` [H,W] 1/m, ``T_j_i`` 4x4); NaN where the point misses view j's domain."""
    device = wp.get_device(device)
    H, W = inv_depth.shape
    uv = wp.empty((H, W), dtype=wp.vec2, device=device)
    d = wp.array(np.ascontiguousarray(inv_depth, dtype=np.float32), dtype=float, device=device)
    wp.launch(reproject_kernel, dim=(H, W), inputs=[rays, d, wp.mat44(*np.asarray(T_j_i, np.float32).ravel()), cam_j], outputs=[uv], device=device)
    out = uv.numpy()
    out[out[..., 0] <= -1.0e3] = np.nan
    return out


@wp.kernel
def guided_upsample_kernel(
    disp: wp.array(dtype=float, ndim=2),  # [h,w] reduced-grid inverse depth (1/m, 0 = unknown)
    image: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] RGB in [0,1]: the guide
    stride: int,
    radius: int,  # cells: the 2r x 2r grid samples around a pixel
    sigma_color: float,  # RGB distance
    sigma_space: float,  # cells
    depth: wp.array(dtype=float, ndim=2),  # [H,W] out: m, 0 = unknown
):
    """Joint bilateral upsampling of one pixel (:func:`mcgs_warp.frontend.depth.upsample_inverse_depth_guided`).
    The weights are float64: a colour mismatch of ~1 (a thin pole no grid sample shares)
    gives exp(-100) or less, zero in float32, yet it must still decide between samples."""
    y, x = wp.tid()
    h = disp.shape[0]
    w = disp.shape[1]
    H = image.shape[0]
    W = image.shape[1]
    o = stride // 2
    gu = wp.float64(x - o) / wp.float64(stride)  # continuous grid coordinates of the pixel
    gv = wp.float64(y - o) / wp.float64(stride)
    cu = int(wp.floor(gu))
    cv = int(wp.floor(gv))
    centre = image[y, x]
    ss = wp.float64(sigma_space) * wp.float64(sigma_space)
    sc = wp.float64(sigma_color) * wp.float64(sigma_color)
    num = wp.float64(0.0)
    den = wp.float64(0.0)
    for dv in range(-radius + 1, radius + 1):
        for du in range(-radius + 1, radius + 1):
            qu = cu + du
            qv = cv + dv
            if qu >= 0 and qu < w and qv >= 0 and qv < h:
                d = disp[qv, qu]
                if d > 0.0:
                    eu = gu - wp.float64(qu)
                    ev = gv - wp.float64(qv)
                    diff = centre - image[wp.min(qv * stride + o, H - 1), wp.min(qu * stride + o, W - 1)]
                    c2 = wp.float64(wp.dot(diff, diff))
                    wgt = wp.exp(wp.float64(-0.5) * (eu * eu + ev * ev) / ss - wp.float64(0.5) * c2 / sc)
                    num += wgt * wp.float64(d)
                    den += wgt
    out = float(0.0)
    if den > wp.float64(0.0):
        inv = num / den
        if inv > wp.float64(0.0):
            out = float(wp.float64(1.0) / wp.max(inv, wp.float64(1.0e-9)))
    depth[y, x] = out


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
    # one source at a time: memory 10 x D x H x W floats, whatever the number of sources
    warped = wp.empty((D, H, W), dtype=float, device=device)
    rows = wp.empty((D, H, W), dtype=window_sums, device=device)
    m1 = wp.full((D, H, W), NO_COST, dtype=float, device=device)
    m2 = wp.full((D, H, W), NO_COST, dtype=float, device=device)
    for s in range(S):
        def warp_and_rows(worker, row0, n, s=s):  # the row sums read only their own rows of warped
            wp.launch(candidate_warp_kernel, dim=(D, n, W), inputs=[ref_rays, depth_w, cand_w, src_w, cams_w, T_w, s, row0], outputs=[warped], device=device)
            wp.launch(window_rows_kernel, dim=(D, n, W), inputs=[ref_w, warped, radius, row0], outputs=[rows], device=device)

        def zncc_band(worker, row0, n):  # reads rows above and below: after all row sums
            wp.launch(window_zncc_kernel, dim=(D, n, W), inputs=[rows, radius, min_std, row0], outputs=[m1, m2], device=device)

        run_row_bands(device, H, warp_and_rows)
        run_row_bands(device, H, zncc_band)
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
        a1 = wp.full((rescore, H, W), NO_COST, dtype=float, device=device)
        a2 = wp.full((rescore, H, W), NO_COST, dtype=float, device=device)
        for s in range(S):
            def adaptive_band(worker, row0, n, s=s):
                wp.launch(adaptive_window_kernel, dim=(rescore, n, W), inputs=[ref_w, colour_w, ref_rays, depth_w, cand_w, picked, src_w, cams_w, T_w, s, radius, gamma_colour, gamma_distance, min_std, row0], outputs=[a1, a2], device=device)

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


@wp.kernel
def point_cost_kernel(
    ref: wp.array(dtype=float, ndim=2),  # [H,W] grey reference, full resolution
    src: wp.array(dtype=float, ndim=3),  # [1,Hs,Ws] grey source
    ref_rays: wp.array(dtype=wp.vec3, ndim=2),  # [H,W] unit-depth rays of the reference
    pix: wp.array(dtype=wp.vec2i),  # [M] reference pixels (x, y)
    rho: wp.array(dtype=float, ndim=2),  # [M,K] inverse-depth candidates per pixel (1/m)
    T_src_ref: wp.mat44,
    cam: Camera,  # the source camera
    radius: int,
    min_std: float,
    cost: wp.array(dtype=float, ndim=2),  # [M,K] out: 1 - ZNCC, or NO_COST
):
    """``1 - ZNCC`` of a ``(2r+1)^2`` window around each listed reference pixel against the
    source, the window lifted to the candidate's fronto-parallel plane (sphere for
    equirectangular) and sampled bilinearly in the source: :func:`sweep` for a few
    pixels and per-pixel hypotheses, at full resolution."""
    m, k = wp.tid()
    p = pix[m]
    r = rho[m, k]
    H = ref.shape[0]
    W = ref.shape[1]
    sums = vec6f()  # n, a, a^2, b, b^2, ab over the valid window pixels
    total = float(0.0)
    if r > 0.0:
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                yy = p[1] + dy
                xx = p[0] + dx
                if yy >= 0 and yy < H and xx >= 0 and xx < W:
                    total += 1.0
                    X = wp.transform_point(T_src_ref, ref_rays[yy, xx] / r)
                    if camera_in_domain(cam, X, NEAR, FAR):
                        uv = camera_project(cam, X)
                        b = sample_bilinear(src, 0, uv[0], uv[1], cam.width, cam.height)
                        if b >= 0.0:
                            a = ref[yy, xx]
                            sums += vec6f(1.0, a, a * a, b, b * b, a * b)
    c = float(NO_COST)
    if sums[0] >= 0.75 * total and sums[0] > 1.0:
        c = zncc_cost(sums[0], sums[1], sums[2], sums[3], sums[4], sums[5], min_std)
    cost[m, k] = c


def refine_points(ref_image: np.ndarray, ref_rays: wp.array, src_image: np.ndarray, src_cam: Camera, T_src_ref: np.ndarray, pix: np.ndarray, rho0: np.ndarray, step_px: float = 0.25, count: int = 12, radius: int = 4, min_std: float = 0.02, device=None):
    """Refine inverse depths ``rho0`` [M] (1/m) of reference pixels ``pix`` [M,2] (x, y)
    at full resolution along the epipolar curve: ``2 count + 1`` candidates ``rho0 + i
    step``, ``step`` per pixel such that the point moves ``step_px`` pixels in the source,
    scored by :func:`point_cost_kernel`; the best is refined by a parabola through its
    neighbours. Returns ``(rho, cost)`` [M]; ``rho`` is 0 where the best candidate is at
    either end of the range (the start was too far off to refine) or none could be scored."""
    from . import reference

    pix = np.asarray(pix, np.int64).reshape(-1, 2)
    rho0 = np.asarray(rho0, np.float64).reshape(-1)
    M = len(pix)
    if M == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.float32)
    T = np.asarray(T_src_ref, np.float64)
    rays = ref_rays.numpy()[pix[:, 1], pix[:, 0]].astype(np.float64)

    def landing(r):  # where each pixel's point at inverse depth r lands in the source (px)
        X = rays / r[:, None]
        return reference.project(src_cam, X @ T[:3, :3].T + T[:3, 3])

    with np.errstate(all="ignore"):
        rate = np.linalg.norm(landing(rho0 * 1.01) - landing(rho0 * 0.99), axis=1) / (0.02 * rho0)  # px per 1/m
    step = np.where(np.isfinite(rate) & (rate > 0), step_px / np.where(rate > 0, rate, 1.0), 0.0)
    device = ref_rays.device if device is None else wp.get_device(device)
    offsets = np.arange(-count, count + 1, dtype=np.float64)
    rho = (rho0[:, None] + offsets[None] * step[:, None]).astype(np.float32)
    cost = wp.empty(rho.shape, dtype=float, device=device)
    inputs = [
        wp.array(np.ascontiguousarray(ref_image, np.float32), dtype=float, device=device),
        wp.array(np.ascontiguousarray(src_image, np.float32)[None], dtype=float, device=device),
        ref_rays,
        wp.array(np.ascontiguousarray(pix, np.int32), dtype=wp.vec2i, device=device),
        wp.array(rho, dtype=float, device=device),
        wp.mat44(*np.asarray(T_src_ref, np.float32).ravel()),
        src_cam,
        int(radius),
        float(min_std),
    ]
    wp.launch(point_cost_kernel, dim=rho.shape, inputs=inputs, outputs=[cost], device=device)
    c = cost.numpy()
    kb = c.argmin(1)
    rows = np.arange(M)
    inner = (kb > 0) & (kb < 2 * count)
    km, kp = np.clip(kb - 1, 0, 2 * count), np.clip(kb + 1, 0, 2 * count)
    cm, c0, cp = c[rows, km], c[rows, kb], c[rows, kp]
    curv = cm - 2 * c0 + cp
    ok = inner & (cm < NO_COST) & (cp < NO_COST) & (curv > 1e-9)
    offset = np.where(ok, np.clip(0.5 * (cm - cp) / np.where(ok, curv, 1.0), -0.5, 0.5), 0.0)
    out = np.where(inner & (c0 < NO_COST) & (step > 0), rho[rows, kb] + offset * step, 0.0).astype(np.float32)
    return out, c0.astype(np.float32)
