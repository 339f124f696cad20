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
   cameras; the window slides down each column, adding and removing a row at a time); ``NO_COST`` where fewer than 3/4 of the window is valid or the reference
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

The dense follow-ups live beside it: :mod:`.propagation` (PatchMatch-style refinement of a
depth map and its multi-view consistency), :mod:`.refine` (reprojection, guided upsampling,
patch comparison and per-point epipolar refinement).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .camera import FAR, NEAR, Camera, camera_in_domain, camera_project
from .mapping import sample_grid

wp.set_module_options({"enable_backward": False})

#: Cost of a hypothesis without information (outside the source, flat window).
NO_COST = wp.constant(3.0)


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


@wp.func
def add_row(
    ref: wp.array(dtype=float, ndim=2),
    warped: wp.array(dtype=float, ndim=3),
    k: int,
    y: int,
    x: int,
    radius: int,
    sign: float,
    t: float,
    n: float,
    sa: float,
    saa: float,
    sb: float,
    sbb: float,
    sab: float,
):
    """Window sums with row ``y`` (the ``2r+1`` pixels around ``x`` that lie in the image)
    added (``sign`` 1) or removed (-1): the in-image count ``t``, the valid count ``n``
    (``warped[k] >= 0``) and a, a^2, b, b^2, ab over the valid samples (a: reference, b:
    ``warped[k]``). Rows outside the image add nothing."""
    H = ref.shape[0]
    W = ref.shape[1]
    if y >= 0 and y < H:
        for dx in range(-radius, radius + 1):
            xx = x + dx
            if xx >= 0 and xx < W:
                t += sign
                b = warped[k, y, xx]
                if b >= 0.0:
                    a = ref[y, xx]
                    n += sign
                    sa += sign * a
                    saa += sign * a * a
                    sb += sign * b
                    sbb += sign * b * b
                    sab += sign * a * b
    return t, n, sa, saa, sb, sbb, sab


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
def zncc_cost_kernel(
    ref: wp.array(dtype=float, ndim=2),  # [H,W] grey reference
    warped: wp.array(dtype=float, ndim=3),  # [N,H,W] warped sources (sweep: [S,D,H,W] flattened)
    radius: int,
    min_std: float,
    min_valid: float,  # fraction of the in-image window that must be valid
    row0: int,
    rows: int,
    fold: int,  # 0: write each cost; 1: fold it into (cost, second) as the lowest two so far
    cost: wp.array(dtype=float, ndim=3),  # [N,H,W]: 1 - ZNCC, or NO_COST (fold: the lowest so far)
    second: wp.array(dtype=float, ndim=3),  # [N,H,W] with fold: the second lowest so far (else unused)
):
    """``1 - ZNCC`` over the ``(2r+1)^2`` window of every pixel of rows ``row0 .. row0 + rows``
    in column ``x`` of warped image ``k`` (``NO_COST`` where less than ``min_valid`` of the
    in-image window is valid, or a window is flat: :func:`zncc_cost`). The window slides down
    the column, a row in and a row out (:func:`add_row`), so a pixel costs ``2 (2r+1)``
    samples instead of ``(2r+1)^2``. With ``fold`` (the propagation's sources, one launch
    each) the cost goes straight into the two lowest over the sources
    (:func:`keep_two_lowest`), with no cost array between."""
    k, x = wp.tid()
    t = float(0.0)  # scalar sums: vector accumulators made these loops 1.5-4x slower on the CPU
    n = float(0.0)
    sa = float(0.0)
    saa = float(0.0)
    sb = float(0.0)
    sbb = float(0.0)
    sab = float(0.0)
    for yy in range(row0 - radius, row0 + radius):  # the first window less its last row
        t, n, sa, saa, sb, sbb, sab = add_row(ref, warped, k, yy, x, radius, 1.0, t, n, sa, saa, sb, sbb, sab)
    for y in range(row0, row0 + rows):
        t, n, sa, saa, sb, sbb, sab = add_row(ref, warped, k, y + radius, x, radius, 1.0, t, n, sa, saa, sb, sbb, sab)
        if y > row0:  # the row that leaves (the first window never held it)
            t, n, sa, saa, sb, sbb, sab = add_row(ref, warped, k, y - radius - 1, x, radius, -1.0, t, n, sa, saa, sb, sbb, sab)
        c = float(NO_COST)
        if n >= min_valid * t and n > 1.0:
            c = zncc_cost(n, sa, saa, sb, sbb, sab, min_std)
        if fold != 0:
            keep_two_lowest(c, cost, second, k, y, x)
        else:
            cost[k, y, x] = c


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

    flat_warped, flat_cost = warped.reshape((S * D, H, W)), cost.reshape((S * D, H, W))

    def cost_band(worker, row0, rows):
        wp.launch(zncc_cost_kernel, dim=(S * D, W), inputs=[ref_w, flat_warped, radius, min_std, 0.75, row0, rows, 0], outputs=[flat_cost, flat_cost], device=device)

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
