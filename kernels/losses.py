"""Per-pixel image losses of the mapping objective (paper eq. 11) and their adjoints.

Images come batched as the renderer writes them: colour ``[C,H,W]`` vec3 and depth
``[C,H,W]`` float (m), padded to the largest camera; camera ``c`` covers rows
``[0, h_c)`` and columns ``[0, w_c)`` (``Camera.height`` / ``Camera.width``). Padding
never enters a loss and gets a zero gradient. Per camera, with its affine exposure
``pred = a * colour + b`` (``exposure[c] = (log a, b)``):

* colour: ``(1 - l_ssim) * mean|pred - target| + l_ssim * (1 - SSIM(pred, target))``,
  means over the camera's ``3 h w`` values (the 3DGS colour term);
* depth: ``mean |D - target_depth|`` over pixels with a target (``> 0``);
* normal: ``mean (1 - <n(D), n(target_depth)>)`` over valid quads. ``n`` is the unit
  normal of the back-projected depth ``X = ray * D`` by forward differences,
  ``n ~ (X[y,x+1] - X[y,x]) x (X[y+1,x] - X[y,x])``; a quad is valid where its three
  depths are known in both maps and both normals are non-degenerate.

SSIM is the 3DGS one, as :func:`mcgs_warp.eval.metrics.ssim` (11x11 Gaussian window,
sigma 1.5, zero padding, ``C1 = 0.01^2``, ``C2 = 0.03^2``), computed separably: a
horizontal pass then a vertical one. Its adjoint blurs the adjoints of the local moments
(``mu_x``, ``E[x^2]``, ``E[xy]``) with the same (symmetric) window. The target's own
moments depend on the keyframe only: :func:`ssim_target_rows_kernel` and
:func:`ssim_target_kernel` make them once per keyframe, with :func:`target_normals_kernel`.

One iteration: ``ssim_moments_rows_kernel -> loss_terms_kernel -> camera_sums_kernel ->
loss_summary_kernel -> blur_rows3_kernel -> image_grad_kernel -> camera_sums_kernel ->
exposure_grad_kernel``. Image kernels take a ``row0`` so that CPU launches can cover bands
of rows from several threads (:mod:`.launch`). The two passes that also reduce
(``loss_terms_kernel``, ``image_grad_kernel``) run a thread per segment of a row (a whole
row on the CPU, a few pixels on CUDA) and sum its pixels in float64; the per-camera sums
then add the segments in a fixed order. No atomics: deterministic on every device and
for any band split.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .camera import Camera

wp.set_module_options({"enable_backward": False, "optimization_level": 3})

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
SSIM_SIZE = 11  # window taps
SSIM_SIGMA = 1.5  # px
_SIZE = wp.constant(SSIM_SIZE)
_RADIUS = wp.constant(SSIM_SIZE // 2)
_C1 = wp.constant(SSIM_C1)
_C2 = wp.constant(SSIM_C2)
_MIN_NORMAL = wp.constant(1.0e-12)  # |n| below which a quad's normal is undefined

# Per-pixel loss terms (float32) and their per-segment / per-camera sums (float64). Slots:
TERM_SSIM = 0  # sum over channels of the SSIM map
TERM_L1 = 1  # sum over channels of |pred - target|
TERM_SQ = 2  # sum over channels of (clip(pred, 0, 1) - target)^2 (for PSNR)
TERM_DEPTH = 3  # |D - target_depth| where the target is known
TERM_NORMAL = 4  # 1 - <n, n_target> of the quad at the pixel
TERM_NORMAL_N = 5  # 1 where that quad is valid
TERM_EXP_LOG_A = 6  # dL/d log a contribution (second pass)
TERM_EXP_B = 7  # dL/d b contribution (second pass)
vec8 = wp.types.vector(8, dtype=wp.float32)
vec8d = wp.types.vector(8, dtype=wp.float64)


def ssim_window(size: int = SSIM_SIZE, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """Normalized 1D Gaussian window [size] (as ``cv2.getGaussianKernel(size, sigma)``)."""
    x = np.arange(size) - (size - 1) / 2
    w = np.exp(-(x * x) / (2 * sigma * sigma))
    return (w / w.sum()).astype(np.float32)


@wp.func
def sgn(x: float):
    """Sign with ``sgn(0) = 0`` (as NumPy; ``wp.sign(0)`` is 1)."""
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return 0.0


@wp.func
def sgn3(v: wp.vec3):
    return wp.vec3(sgn(v[0]), sgn(v[1]), sgn(v[2]))


@wp.func
def blur(a: wp.array(dtype=wp.vec3, ndim=3), window: wp.array(dtype=float), c: int, y: int, x: int, dy: int, dx: int, extent: int):
    """One pass of the zero-padded window at (c, y, x) along the unit axis (dy, dx):
    taps whose coordinate along that axis leaves [0, extent) count as zero."""
    i = y * dy + x * dx
    if i >= _RADIUS and i + _RADIUS < extent:  # interior: symmetric taps in pairs, no bounds tests
        s = window[_RADIUS] * a[c, y, x]
        for k in range(_RADIUS):
            o = _RADIUS - k
            s += window[k] * (a[c, y - o * dy, x - o * dx] + a[c, y + o * dy, x + o * dx])
        return s
    s = wp.vec3(0.0)
    for k in range(_SIZE):
        o = k - _RADIUS
        if i + o >= 0 and i + o < extent:
            s += window[k] * a[c, y + o * dy, x + o * dx]
    return s


@wp.func
def blur_row(a: wp.array(dtype=wp.vec3, ndim=3), window: wp.array(dtype=float), c: int, y: int, x: int, width: int):
    """Horizontal pass over columns [0, width)."""
    return blur(a, window, c, y, x, 0, 1, width)


@wp.func
def blur_col(a: wp.array(dtype=wp.vec3, ndim=3), window: wp.array(dtype=float), c: int, y: int, x: int, height: int):
    """Vertical pass over rows [0, height)."""
    return blur(a, window, c, y, x, 1, 0, height)


@wp.func
def normal_quad(
    depth: wp.array(dtype=float, ndim=3),
    rays: wp.array(dtype=wp.vec3, ndim=3),
    target_normals: wp.array(dtype=wp.vec3, ndim=3),
    c: int,
    y: int,
    x: int,
    width: int,
    height: int,
):
    """Normal term of the quad whose corner is (y, x): ``(value, valid, g_a, g_b)`` with
    ``value = 1 - <n_hat, n_target>`` and ``g_a``, ``g_b`` the gradients of ``-<n_hat,
    n_target>`` w.r.t. the edges ``a = X[y,x+1] - X[y,x]`` and ``b = X[y+1,x] - X[y,x]``
    (all zero where the quad is not valid)."""
    zero = wp.vec3(0.0)
    if x + 1 >= width or y + 1 >= height:
        return 0.0, 0.0, zero, zero
    nt = target_normals[c, y, x]
    d0 = depth[c, y, x]
    d1 = depth[c, y, x + 1]
    d2 = depth[c, y + 1, x]
    if wp.length_sq(nt) == 0.0 or d0 <= 0.0 or d1 <= 0.0 or d2 <= 0.0:
        return 0.0, 0.0, zero, zero
    X0 = d0 * rays[c, y, x]
    a = d1 * rays[c, y, x + 1] - X0
    b = d2 * rays[c, y + 1, x] - X0
    n = wp.cross(a, b)
    length = wp.length(n)
    if length <= _MIN_NORMAL:
        return 0.0, 0.0, zero, zero
    n_hat = n / length
    # d(-<n_hat, nt>)/dn = -(I - n_hat n_hat^T) nt / |n|; then d(a x b)/da^T g = b x g, /db^T g = g x a
    g_n = (wp.dot(n_hat, nt) * n_hat - nt) / length
    return 1.0 - wp.dot(n_hat, nt), 1.0, wp.cross(b, g_n), wp.cross(g_n, a)


@wp.func
def moment_tap(color: wp.array(dtype=wp.vec3, ndim=3), target: wp.array(dtype=wp.vec3, ndim=3), a: float, b: wp.vec3, c: int, y: int, x: int):
    """``(p, p^2, p t)`` at one pixel for ``p = a * colour + b`` (the SSIM moments' integrands)."""
    p = a * color[c, y, x] + b
    return p, wp.cw_mul(p, p), wp.cw_mul(p, target[c, y, x])


# --- per keyframe: target statistics --------------------------------------------------


@wp.kernel
def ssim_target_rows_kernel(
    target: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] image
    cameras: wp.array(dtype=Camera),  # [C]
    window: wp.array(dtype=float),  # [11]
    row0: int,
    h_t: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: horizontal pass of the target
    h_tt: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: ... of its square
):
    c, yb, x = wp.tid()
    y = yb + row0
    cam = cameras[c]
    s1 = wp.vec3(0.0)
    s2 = wp.vec3(0.0)
    if x < cam.width and y < cam.height:
        for k in range(_SIZE):
            u = x + k - _RADIUS
            if u >= 0 and u < cam.width:
                t = target[c, y, u]
                s1 += window[k] * t
                s2 += window[k] * wp.cw_mul(t, t)
    h_t[c, y, x] = s1
    h_tt[c, y, x] = s2


@wp.kernel
def ssim_target_kernel(
    cameras: wp.array(dtype=Camera),
    window: wp.array(dtype=float),
    row0: int,
    h_t: wp.array(dtype=wp.vec3, ndim=3),
    h_tt: wp.array(dtype=wp.vec3, ndim=3),
    mu: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: local mean of the target
    var: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: local variance E[t^2] - mu^2
):
    c, yb, x = wp.tid()
    y = yb + row0
    cam = cameras[c]
    m = wp.vec3(0.0)
    v = wp.vec3(0.0)
    if x < cam.width and y < cam.height:
        m = blur_col(h_t, window, c, y, x, cam.height)
        v = blur_col(h_tt, window, c, y, x, cam.height) - wp.cw_mul(m, m)
    mu[c, y, x] = m
    var[c, y, x] = v


@wp.kernel
def target_normals_kernel(
    target_depth: wp.array(dtype=float, ndim=3),  # [C,H,W] m, 0 = none
    rays: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] unit-depth rays
    cameras: wp.array(dtype=Camera),
    row0: int,
    normals: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: unit normal of the quad at (y, x), 0 = none
):
    c, yb, x = wp.tid()
    y = yb + row0
    cam = cameras[c]
    n = wp.vec3(0.0)
    if x + 1 < cam.width and y + 1 < cam.height:
        d0 = target_depth[c, y, x]
        d1 = target_depth[c, y, x + 1]
        d2 = target_depth[c, y + 1, x]
        if d0 > 0.0 and d1 > 0.0 and d2 > 0.0:
            X0 = d0 * rays[c, y, x]
            m = wp.cross(d1 * rays[c, y, x + 1] - X0, d2 * rays[c, y + 1, x] - X0)
            length = wp.length(m)
            if length > _MIN_NORMAL:
                n = m / length
    normals[c, y, x] = n


# --- per iteration ----------------------------------------------------------------------


@wp.kernel
def ssim_moments_rows_kernel(
    color: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] rendered
    target: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W]
    exposure: wp.array(dtype=float, ndim=2),  # [C,2] (log a, b)
    cameras: wp.array(dtype=Camera),
    window: wp.array(dtype=float),
    row0: int,
    h_x: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: horizontal pass of pred
    h_xx: wp.array(dtype=wp.vec3, ndim=3),  # ... of pred^2
    h_xy: wp.array(dtype=wp.vec3, ndim=3),  # ... of pred * target
):
    c, yb, x = wp.tid()
    y = yb + row0
    cam = cameras[c]
    s1 = wp.vec3(0.0)
    s2 = wp.vec3(0.0)
    s3 = wp.vec3(0.0)
    if x < cam.width and y < cam.height:
        a = wp.exp(exposure[c, 0])
        b = wp.vec3(exposure[c, 1])
        if x >= _RADIUS and x + _RADIUS < cam.width:  # interior: symmetric taps in pairs
            p, pp, pt = moment_tap(color, target, a, b, c, y, x)
            s1 = window[_RADIUS] * p
            s2 = window[_RADIUS] * pp
            s3 = window[_RADIUS] * pt
            for k in range(_RADIUS):
                p1, pp1, pt1 = moment_tap(color, target, a, b, c, y, x + k - _RADIUS)
                p2, pp2, pt2 = moment_tap(color, target, a, b, c, y, x + _RADIUS - k)
                s1 += window[k] * (p1 + p2)
                s2 += window[k] * (pp1 + pp2)
                s3 += window[k] * (pt1 + pt2)
        else:
            for k in range(_SIZE):
                u = x + k - _RADIUS
                if u >= 0 and u < cam.width:
                    p, pp, pt = moment_tap(color, target, a, b, c, y, u)
                    s1 += window[k] * p
                    s2 += window[k] * pp
                    s3 += window[k] * pt
    h_x[c, y, x] = s1
    h_xx[c, y, x] = s2
    h_xy[c, y, x] = s3


@wp.kernel
def loss_terms_kernel(
    color: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] rendered
    depth: wp.array(dtype=float, ndim=3),  # [C,H,W] rendered, m
    target: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W]
    target_depth: wp.array(dtype=float, ndim=3),  # [C,H,W] m, 0 = none
    target_mu: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] from ssim_target_kernel
    target_var: wp.array(dtype=wp.vec3, ndim=3),
    target_normals: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] from target_normals_kernel
    rays: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] unit-depth rays
    exposure: wp.array(dtype=float, ndim=2),  # [C,2]
    cameras: wp.array(dtype=Camera),
    window: wp.array(dtype=float),
    lambda_ssim: float,  # 0: no SSIM (h_* are not read, d_* are zero)
    segment: int,  # pixels of a row per thread
    row0: int,
    h_x: wp.array(dtype=wp.vec3, ndim=3),  # horizontal passes from ssim_moments_rows_kernel
    h_xx: wp.array(dtype=wp.vec3, ndim=3),
    h_xy: wp.array(dtype=wp.vec3, ndim=3),
    d_mx: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: dL/d mu_x (SSIM part of the loss)
    d_mxx: wp.array(dtype=wp.vec3, ndim=3),  # out: dL/d E[x^2]
    d_mxy: wp.array(dtype=wp.vec3, ndim=3),  # out: dL/d E[xy]
    quad_a: wp.array(dtype=wp.vec3, ndim=3),  # out: unweighted normal adjoint of edge a of the quad at the pixel
    quad_b: wp.array(dtype=wp.vec3, ndim=3),  # out: ... of edge b
    sums: wp.array(dtype=vec8d, ndim=3),  # [C,H,S] out: loss terms summed over each segment
):
    """First pass over segments of ``segment`` pixels of a row (dim ``(C, rows, S)``)."""
    c, yb, s = wp.tid()
    y = yb + row0
    cam = cameras[c]
    a = wp.exp(exposure[c, 0])
    b = wp.vec3(exposure[c, 1])
    zero = wp.vec3(0.0)
    acc = vec8d()
    for x in range(s * segment, wp.min((s + 1) * segment, color.shape[2])):
        g_mx = zero
        g_mxx = zero
        g_mxy = zero
        ga = zero
        gb = zero
        ssim_sum = float(0.0)
        l1 = float(0.0)
        sq = float(0.0)
        depth_abs = float(0.0)
        normal = float(0.0)
        valid = float(0.0)
        if x < cam.width and y < cam.height:
            p = a * color[c, y, x] + b
            t = target[c, y, x]
            diff = p - t
            l1 = wp.abs(diff[0]) + wp.abs(diff[1]) + wp.abs(diff[2])
            e = wp.vec3(wp.clamp(p[0], 0.0, 1.0), wp.clamp(p[1], 0.0, 1.0), wp.clamp(p[2], 0.0, 1.0)) - t
            sq = wp.dot(e, e)
            dt = target_depth[c, y, x]
            if dt > 0.0:
                depth_abs = wp.abs(depth[c, y, x] - dt)
            normal, valid, ga, gb = normal_quad(depth, rays, target_normals, c, y, x, cam.width, cam.height)
            if lambda_ssim > 0.0:
                mx = blur_col(h_x, window, c, y, x, cam.height)
                mxx = blur_col(h_xx, window, c, y, x, cam.height)
                mxy = blur_col(h_xy, window, c, y, x, cam.height)
                my = target_mu[c, y, x]
                mxmy = wp.cw_mul(mx, my)
                A1 = 2.0 * mxmy + wp.vec3(_C1)
                A2 = 2.0 * (mxy - mxmy) + wp.vec3(_C2)  # 2 sxy + C2, sxy = E[xy] - mx my
                B1 = wp.cw_mul(mx, mx) + wp.cw_mul(my, my) + wp.vec3(_C1)
                B2 = (mxx - wp.cw_mul(mx, mx)) + target_var[c, y, x] + wp.vec3(_C2)  # sxx + syy + C2
                B = wp.cw_mul(B1, B2)
                S = wp.cw_div(wp.cw_mul(A1, A2), B)  # per channel
                ssim_sum = S[0] + S[1] + S[2]
                dS_dmx = 2.0 * wp.cw_div(wp.cw_mul(my, A2), B) - 2.0 * wp.cw_div(wp.cw_mul(S, mx), B1)
                dS_dsxx = -wp.cw_div(S, B2)
                dS_dsxy = 2.0 * wp.cw_div(A1, B)
                g = -lambda_ssim / float(3 * cam.width * cam.height)  # dL/dS per value
                # chain to the raw moments: sxx = E[x^2] - mx^2, sxy = E[xy] - mx my
                g_mx = g * (dS_dmx - 2.0 * wp.cw_mul(mx, dS_dsxx) - wp.cw_mul(my, dS_dsxy))
                g_mxx = g * dS_dsxx
                g_mxy = g * dS_dsxy
        d_mx[c, y, x] = g_mx
        d_mxx[c, y, x] = g_mxx
        d_mxy[c, y, x] = g_mxy
        quad_a[c, y, x] = ga
        quad_b[c, y, x] = gb
        t8 = vec8(ssim_sum, l1, sq, depth_abs, normal, valid, 0.0, 0.0)
        for i in range(6):
            acc[i] = acc[i] + wp.float64(t8[i])
    sums[c, y, s] = acc


@wp.kernel
def blur_rows3_kernel(
    cameras: wp.array(dtype=Camera),
    window: wp.array(dtype=float),
    row0: int,
    a1: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] in
    a2: wp.array(dtype=wp.vec3, ndim=3),
    a3: wp.array(dtype=wp.vec3, ndim=3),
    b1: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: horizontal passes of a1..a3
    b2: wp.array(dtype=wp.vec3, ndim=3),
    b3: wp.array(dtype=wp.vec3, ndim=3),
):
    c, yb, x = wp.tid()
    y = yb + row0
    cam = cameras[c]
    zero = wp.vec3(0.0)
    if x < cam.width and y < cam.height:
        b1[c, y, x] = blur_row(a1, window, c, y, x, cam.width)
        b2[c, y, x] = blur_row(a2, window, c, y, x, cam.width)
        b3[c, y, x] = blur_row(a3, window, c, y, x, cam.width)
    else:
        b1[c, y, x] = zero
        b2[c, y, x] = zero
        b3[c, y, x] = zero


@wp.kernel
def image_grad_kernel(
    color: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] rendered
    depth: wp.array(dtype=float, ndim=3),  # [C,H,W] rendered, m
    target: wp.array(dtype=wp.vec3, ndim=3),
    target_depth: wp.array(dtype=float, ndim=3),
    rays: wp.array(dtype=wp.vec3, ndim=3),
    exposure: wp.array(dtype=float, ndim=2),  # [C,2]
    cameras: wp.array(dtype=Camera),
    window: wp.array(dtype=float),
    lambda_ssim: float,
    lambda_depth: float,
    inv_depth_count: wp.array(dtype=float),  # [C] 1 / #pixels with a target depth (0: none)
    normal_weight: wp.array(dtype=float),  # [C] lambda_normal / #valid quads (loss_summary_kernel)
    segment: int,  # pixels of a row per thread
    row0: int,
    b_mx: wp.array(dtype=wp.vec3, ndim=3),  # horizontal passes of d_mx, d_mxx, d_mxy
    b_mxx: wp.array(dtype=wp.vec3, ndim=3),
    b_mxy: wp.array(dtype=wp.vec3, ndim=3),
    quad_a: wp.array(dtype=wp.vec3, ndim=3),  # from loss_terms_kernel
    quad_b: wp.array(dtype=wp.vec3, ndim=3),
    grad_color: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: dL/d rendered colour
    grad_depth: wp.array(dtype=float, ndim=3),  # [C,H,W] out: dL/d rendered depth
    sums: wp.array(dtype=vec8d, ndim=3),  # [C,H,S] out: exposure terms (slots TERM_EXP_*) per segment
):
    """Second pass over segments of ``segment`` pixels of a row (dim ``(C, rows, S)``)."""
    c, yb, s = wp.tid()
    y = yb + row0
    cam = cameras[c]
    a = wp.exp(exposure[c, 0])
    b = wp.vec3(exposure[c, 1])
    acc = vec8d()
    for x in range(s * segment, wp.min((s + 1) * segment, color.shape[2])):
        gC = wp.vec3(0.0)
        gD = float(0.0)
        exp_log_a = float(0.0)
        exp_b = float(0.0)
        if x < cam.width and y < cam.height:
            col = color[c, y, x]
            p = a * col + b
            t = target[c, y, x]
            gp = ((1.0 - lambda_ssim) / float(3 * cam.width * cam.height)) * sgn3(p - t)  # dL/d pred
            if lambda_ssim > 0.0:
                gp += blur_col(b_mx, window, c, y, x, cam.height)
                gp += 2.0 * wp.cw_mul(p, blur_col(b_mxx, window, c, y, x, cam.height))
                gp += wp.cw_mul(t, blur_col(b_mxy, window, c, y, x, cam.height))
            gC = a * gp
            exp_log_a = a * wp.dot(gp, col)
            exp_b = gp[0] + gp[1] + gp[2]
            dt = target_depth[c, y, x]
            if dt > 0.0:
                gD = lambda_depth * inv_depth_count[c] * sgn(depth[c, y, x] - dt)
            # normal term: this pixel is the corner of quad (y, x), the x+1 neighbour of
            # quad (y, x-1) and the y+1 neighbour of quad (y-1, x)
            gX = -(quad_a[c, y, x] + quad_b[c, y, x])
            if x > 0:
                gX += quad_a[c, y, x - 1]
            if y > 0:
                gX += quad_b[c, y - 1, x]
            if wp.length_sq(gX) > 0.0:  # (a pixel without a ray, NaN, is in no valid quad)
                gD += normal_weight[c] * wp.dot(gX, rays[c, y, x])
        grad_color[c, y, x] = gC
        grad_depth[c, y, x] = gD
        acc[6] = acc[6] + wp.float64(exp_log_a)
        acc[7] = acc[7] + wp.float64(exp_b)
    sums[c, y, s] = acc


@wp.kernel
def camera_sums_kernel(
    segments: wp.array(dtype=vec8d, ndim=3),  # [C,H,S] per-segment sums
    cameras: wp.array(dtype=Camera),
    sums: wp.array(dtype=vec8d),  # [C] out
):
    """Per-camera sums over the camera's rows, in a fixed order (launch with dim C)."""
    c = wp.tid()
    s = vec8d()
    for y in range(cameras[c].height):
        for k in range(segments.shape[2]):
            s += segments[c, y, k]
    sums[c] = s


@wp.kernel
def loss_summary_kernel(
    sums: wp.array(dtype=vec8d),  # [C] per-camera sums of the loss terms
    cameras: wp.array(dtype=Camera),
    inv_depth_count: wp.array(dtype=float),  # [C] 1 / #pixels with a target depth (0: none)
    lambda_ssim: float,
    lambda_depth: float,
    lambda_normal: float,
    losses: wp.array(dtype=wp.vec4d),  # [C] out: (colour, depth, normal) loss terms, mean squared error
    normal_weight: wp.array(dtype=float),  # [C] out: lambda_normal / #valid quads
):
    c = wp.tid()
    s = sums[c]
    cam = cameras[c]
    n = wp.float64(3 * cam.width * cam.height)
    ls = wp.float64(lambda_ssim)
    color = (wp.float64(1.0) - ls) * s[1] / n
    if lambda_ssim > 0.0:
        color += ls * (wp.float64(1.0) - s[0] / n)
    count = wp.max(s[5], wp.float64(1.0))
    losses[c] = wp.vec4d(color, wp.float64(lambda_depth * inv_depth_count[c]) * s[3], wp.float64(lambda_normal) * s[4] / count, s[2] / n)
    normal_weight[c] = float(wp.float64(lambda_normal) / count)


@wp.kernel
def exposure_grad_kernel(
    sums: wp.array(dtype=vec8d),  # [C] sums of the second pass
    grad: wp.array(dtype=float, ndim=2),  # [C,2] out: dL/d (log a, b)
):
    c = wp.tid()
    grad[c, 0] = float(sums[c][6])
    grad[c, 1] = float(sums[c][7])
