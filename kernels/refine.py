"""Per-pixel reprojection, image-guided depth upsampling, patch comparison and epipolar
point refinement between views of any camera model.

:func:`reproject` moves grid pixels with their inverse depth into another view
(:func:`reproject_kernel`); :func:`guided_upsample_kernel` fills a full-resolution depth map
from a coarse one guided by the image.

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
from .sweep import NO_COST, sample_bilinear, zncc_cost

wp.set_module_options({"enable_backward": False})

vec6f = wp.types.vector(6, dtype=wp.float32)


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
