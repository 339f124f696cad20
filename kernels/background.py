"""A background at infinity behind the splats: colour by world direction, and its adjoint.

Outdoor images show sky and far geometry that no Gaussian of a bounded map should stand
for (beyond the far plane, or without a depth to put a Gaussian at). As outdoor splatting
systems do with a sky model, whatever light the splats leave through (transmittance
``T = 1 - alpha``) comes from a background that depends only on the viewing direction
``d`` in the world frame, so every view of the rig sees the same sky wherever it is:

    C_out = C_splats + (1 - alpha) * B(d),   B(d) = sum_k coeffs[k] * Y_k(d) + cube(d)

with ``Y_k`` the 16 real spherical harmonics up to degree 3 (the 3DGS basis and sign
convention): smooth, free of any parametrization's poles, so it needs no choice of the
world's up axis. A bright, cloudy sky has more detail than degree 3 holds, so an optional
environment cube map adds it: ``coeffs[16:]`` are 6 faces of R x R RGB texels (face
``2a + (d_a < 0)`` for the dominant axis ``a``, texel coordinates from the other two axes
in cyclic order divided by ``|d_a|``), bilinearly interpolated and clamped at a face's
edge. It starts at zero (the harmonics carry what no view constrains) and, like them,
needs no up axis. ``len(coeffs) = 16`` is the harmonics alone. ``d`` is the pixel's ray (camera frame, ``rays`` [C,H,W]) rotated by
``R_w_c``, normalized. Pixels without a ray (NaN, beyond a fisheye's domain) or outside a
camera's image get no background.

The adjoint of ``C_out`` w.r.t. the splats' colour is the identity, w.r.t. alpha
``-dL/dC_out . B(d)`` (handed to :func:`~mcgs_warp.kernels.splat.blend_backward` as its
``grad_alpha``), w.r.t. ``coeffs[k]`` the sum over pixels of ``(1 - alpha) Y_k(d) dL/dC_out`` (and of the bilinear weight for a
cube texel).
"""

from __future__ import annotations

import warp as wp

from .camera import Camera

N_COEFFS = 16  # real spherical harmonics up to degree 3

sh16 = wp.types.vector(length=16, dtype=wp.float32)


@wp.func
def sh_basis(d: wp.vec3):
    """The 16 real spherical harmonics of degree <= 3 at the unit direction ``d``."""
    x = d[0]
    y = d[1]
    z = d[2]
    xx = x * x
    yy = y * y
    zz = z * z
    b = sh16()
    b[0] = 0.28209479177387814
    b[1] = -0.4886025119029199 * y
    b[2] = 0.4886025119029199 * z
    b[3] = -0.4886025119029199 * x
    b[4] = 1.0925484305920792 * x * y
    b[5] = -1.0925484305920792 * y * z
    b[6] = 0.31539156525252005 * (2.0 * zz - xx - yy)
    b[7] = -1.0925484305920792 * x * z
    b[8] = 0.5462742152960396 * (xx - yy)
    b[9] = -0.5900435899266435 * y * (3.0 * xx - yy)
    b[10] = 2.890611442640554 * x * y * z
    b[11] = -0.4570457994644658 * y * (4.0 * zz - xx - yy)
    b[12] = 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
    b[13] = -0.4570457994644658 * x * (4.0 * zz - xx - yy)
    b[14] = 1.445305721320277 * z * (xx - yy)
    b[15] = -0.5900435899266435 * x * (xx - 3.0 * yy)
    return b


@wp.func
def world_direction(ray: wp.vec3, T_c_w: wp.mat44):
    """Unit world-frame direction of the camera-frame ``ray`` (``R_w_c = R_c_w^T``)."""
    d = wp.vec3(
        T_c_w[0, 0] * ray[0] + T_c_w[1, 0] * ray[1] + T_c_w[2, 0] * ray[2],
        T_c_w[0, 1] * ray[0] + T_c_w[1, 1] * ray[1] + T_c_w[2, 1] * ray[2],
        T_c_w[0, 2] * ray[0] + T_c_w[1, 2] * ray[1] + T_c_w[2, 2] * ray[2],
    )
    return wp.normalize(d)


@wp.func
def cube_coords(d: wp.vec3, R: int):
    """(face, x, y): the cube face of the unit direction ``d`` and its continuous texel
    coordinates on that face, clamped to [0, R-1]."""
    ax = wp.abs(d[0])
    ay = wp.abs(d[1])
    az = wp.abs(d[2])
    a = int(2)
    m = az
    s = d[2]
    b = d[0]
    c = d[1]
    if ax >= ay and ax >= az:
        a = 0
        m = ax
        s = d[0]
        b = d[1]
        c = d[2]
    elif ay >= az:
        a = 1
        m = ay
        s = d[1]
        b = d[2]
        c = d[0]
    face = 2 * a
    if s < 0.0:
        face = face + 1
    hi = float(R - 1)
    x = wp.clamp((b / m + 1.0) * 0.5 * float(R) - 0.5, 0.0, hi)
    y = wp.clamp((c / m + 1.0) * 0.5 * float(R) - 0.5, 0.0, hi)
    return wp.vec3(float(face), x, y)


@wp.func
def cube_corner(fxy: wp.vec3, R: int, corner: int):
    """(index into coeffs, bilinear weight) of one of the 4 texels around ``fxy``."""
    x0 = wp.min(int(wp.floor(fxy[1])), R - 2)
    y0 = wp.min(int(wp.floor(fxy[2])), R - 2)
    fx = fxy[1] - float(x0)
    fy = fxy[2] - float(y0)
    dx = corner % 2
    dy = corner / 2
    wx = 1.0 - fx
    if dx == 1:
        wx = fx
    wy = 1.0 - fy
    if dy == 1:
        wy = fy
    return 16 + (int(fxy[0]) * R + y0 + dy) * R + x0 + dx, wx * wy


@wp.func
def background_colour(d: wp.vec3, coeffs: wp.array(dtype=wp.vec3), R: int):
    b = sh_basis(d)
    bg = wp.vec3(0.0)
    for k in range(16):
        bg += b[k] * coeffs[k]
    if R > 1:
        fxy = cube_coords(d, R)
        for corner in range(4):
            i, w = cube_corner(fxy, R, corner)
            bg += w * coeffs[i]
    return bg


@wp.func
def has_background(cam: Camera, ray: wp.vec3, y: int, x: int):
    return x < cam.width and y < cam.height and wp.isfinite(ray) and wp.length(ray) > 0.0


TRANSPARENT_EPS = wp.constant(1e-6)  # transmittance below which a pixel's background weight is skipped in the backward pass


@wp.kernel
def composite_kernel(
    color: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] splats' colour
    alpha: wp.array(dtype=float, ndim=3),  # [C,H,W]
    rays: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] camera frame
    viewmats: wp.array(dtype=wp.mat44),  # [C] T_c_w
    cameras: wp.array(dtype=Camera),
    coeffs: wp.array(dtype=wp.vec3),  # [16 + 6 R^2] RGB per harmonic, then the cube's texels
    R: int,  # cube face size (0: none)
    row0: int,  # first image row of this launch (row bands on the CPU)
    out: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W]
    background: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: B(d) per pixel (0: none), for the backward pass
):
    c, yy, x = wp.tid()
    y = row0 + yy
    ray = rays[c, y, x]
    value = color[c, y, x]
    bg = wp.vec3(0.0)
    if has_background(cameras[c], ray, y, x):
        bg = background_colour(world_direction(ray, viewmats[c]), coeffs, R)
        value = value + (1.0 - alpha[c, y, x]) * bg
    out[c, y, x] = value
    background[c, y, x] = bg


@wp.kernel(enable_backward=False)
def composite_backward_kernel(
    alpha: wp.array(dtype=float, ndim=3),
    rays: wp.array(dtype=wp.vec3, ndim=3),
    viewmats: wp.array(dtype=wp.mat44),
    cameras: wp.array(dtype=Camera),
    R: int,
    background: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] B(d), as the forward pass wrote it
    grad_out: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] dL/dC_out
    row0: int,
    worker: int,
    grad_alpha: wp.array(dtype=float, ndim=3),  # [C,H,W] out
    grad_coeffs: wp.array(dtype=wp.vec3, ndim=2),  # [C*H, 16] out: per image row (few atomics), summed after
    grad_cube: wp.array(dtype=wp.vec3, ndim=2),  # [workers, 16 + 6 R^2] out (first 16 unused): per worker, summed after
):
    c, yy, x = wp.tid()
    y = row0 + yy
    ray = rays[c, y, x]
    if not has_background(cameras[c], ray, y, x):
        grad_alpha[c, y, x] = 0.0
        return
    g = grad_out[c, y, x]
    grad_alpha[c, y, x] = -wp.dot(g, background[c, y, x])
    t = 1.0 - alpha[c, y, x]
    if t < TRANSPARENT_EPS:  # the background is hidden: its weights get nothing measurable
        return
    d = world_direction(ray, viewmats[c])
    b = sh_basis(d)
    row = c * alpha.shape[1] + y
    for k in range(16):
        wp.atomic_add(grad_coeffs, row, k, (t * b[k]) * g)
    if R > 1:
        fxy = cube_coords(d, R)
        for corner in range(4):
            i, w = cube_corner(fxy, R, corner)
            wp.atomic_add(grad_cube, worker, i, (t * w) * g)


@wp.kernel(enable_backward=False)
def sum_rows_kernel(rows: wp.array(dtype=wp.vec3, ndim=2), total: wp.array(dtype=wp.vec3)):
    r, k = wp.tid()
    wp.atomic_add(total, k, rows[r, k])


def n_coeffs(cube_size: int = 0) -> int:
    """Length of a background's ``coeffs``: 16 harmonics, then 6 faces of ``cube_size``^2 texels."""
    return N_COEFFS + (6 * cube_size * cube_size if cube_size > 1 else 0)


def cube_size(coeffs: wp.array) -> int:
    """The cube face size R of ``coeffs`` (0: harmonics alone)."""
    extra = coeffs.shape[0] - N_COEFFS
    R = int(round((extra / 6) ** 0.5)) if extra > 0 else 0
    if n_coeffs(R) != coeffs.shape[0]:
        raise ValueError(f"background: expected 16 + 6 R^2 coefficients, got {coeffs.shape[0]}")
    return R


def composite(color: wp.array, alpha: wp.array, rays: wp.array, viewmats: wp.array, cameras: wp.array, coeffs: wp.array, out: wp.array | None = None, background: wp.array | None = None) -> wp.array:
    """``color + (1 - alpha) B(d)`` [C,H,W] vec3 (see the module docstring); ``background``
    ([C,H,W] vec3, optional) receives ``B(d)`` for :func:`composite_backward`. On the CPU the
    rows are split over all cores."""
    from .launch import run_row_bands

    if out is None:
        out = wp.empty_like(color)
    if background is None:
        background = wp.empty_like(color)
    C, H, W = alpha.shape
    R = cube_size(coeffs)

    def band(worker, row0, rows):
        wp.launch(composite_kernel, dim=(C, rows, W), inputs=[color, alpha, rays, viewmats, cameras, coeffs, R, row0], outputs=[out, background], device=color.device)

    run_row_bands(color.device, H, band)
    return out


def composite_backward(alpha: wp.array, rays: wp.array, viewmats: wp.array, cameras: wp.array, coeffs: wp.array, grad_out: wp.array, background: wp.array | None = None) -> tuple[wp.array, wp.array]:
    """``(dL/dalpha [C,H,W], dL/dcoeffs [len(coeffs)] vec3)`` from ``dL/dC_out`` [C,H,W]; the
    gradient w.r.t. the splats' colour is ``grad_out`` itself. ``background``: ``B(d)`` as
    :func:`composite` wrote it for these views and ``coeffs`` (recomputed when not given)."""
    from .launch import band_workers, run_row_bands

    C, H, W = alpha.shape
    dev = alpha.device
    R = cube_size(coeffs)
    if background is None:
        background = wp.empty((C, H, W), dtype=wp.vec3, device=dev)
        composite(wp.zeros((C, H, W), dtype=wp.vec3, device=dev), alpha, rays, viewmats, cameras, coeffs, background=background)
    grad_alpha = wp.empty((C, H, W), dtype=float, device=dev)
    rows = wp.zeros((C * H, N_COEFFS), dtype=wp.vec3, device=dev)
    per_worker = wp.zeros((band_workers(dev, H), coeffs.shape[0]), dtype=wp.vec3, device=dev)

    def band(worker, row0, n):
        wp.launch(composite_backward_kernel, dim=(C, n, W), inputs=[alpha, rays, viewmats, cameras, R, background, grad_out, row0, worker], outputs=[grad_alpha, rows, per_worker], device=dev)

    run_row_bands(dev, H, band)
    grad_coeffs = wp.zeros(coeffs.shape[0], dtype=wp.vec3, device=dev)
    wp.launch(sum_rows_kernel, dim=(C * H, N_COEFFS), inputs=[rows], outputs=[grad_coeffs], device=dev)
    if R > 1:
        wp.launch(sum_rows_kernel, dim=per_worker.shape, inputs=[per_worker], outputs=[grad_coeffs], device=dev)
    return grad_alpha, grad_coeffs
