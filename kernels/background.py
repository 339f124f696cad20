"""A background at infinity behind the splats: colour by world direction, and its adjoint.

Outdoor images show sky and far geometry that no Gaussian of a bounded map should stand
for (beyond the far plane, or without a depth to put a Gaussian at). As outdoor splatting
systems do with a sky model, whatever light the splats leave through (transmittance
``T = 1 - alpha``) comes from a background that depends only on the viewing direction
``d`` in the world frame, so every view of the rig sees the same sky wherever it is:

    C_out = C_splats + (1 - alpha) * B(d),   B(d) = sum_k coeffs[k] * Y_k(d)

with ``Y_k`` the 16 real spherical harmonics up to degree 3 (the 3DGS basis and sign
convention): smooth, free of any parametrization's poles, so it needs no choice of the
world's up axis. ``d`` is the pixel's ray (camera frame, ``rays`` [C,H,W]) rotated by
``R_w_c``, normalized. Pixels without a ray (NaN, beyond a fisheye's domain) or outside a
camera's image get no background.

The adjoint of ``C_out`` w.r.t. the splats' colour is the identity, w.r.t. alpha
``-dL/dC_out . B(d)`` (handed to :func:`~mcgs_warp.kernels.splat.blend_backward` as its
``grad_alpha``), w.r.t. ``coeffs[k]`` the sum over pixels of ``(1 - alpha) Y_k(d) dL/dC_out``.
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
def has_background(cam: Camera, ray: wp.vec3, y: int, x: int):
    return x < cam.width and y < cam.height and wp.isfinite(ray) and wp.length(ray) > 0.0


@wp.kernel
def composite_kernel(
    color: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] splats' colour
    alpha: wp.array(dtype=float, ndim=3),  # [C,H,W]
    rays: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] camera frame
    viewmats: wp.array(dtype=wp.mat44),  # [C] T_c_w
    cameras: wp.array(dtype=Camera),
    coeffs: wp.array(dtype=wp.vec3),  # [16] RGB per harmonic
    out: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W]
):
    c, y, x = wp.tid()
    ray = rays[c, y, x]
    value = color[c, y, x]
    if has_background(cameras[c], ray, y, x):
        b = sh_basis(world_direction(ray, viewmats[c]))
        bg = wp.vec3(0.0)
        for k in range(16):
            bg += b[k] * coeffs[k]
        value = value + (1.0 - alpha[c, y, x]) * bg
    out[c, y, x] = value


@wp.kernel(enable_backward=False)
def composite_backward_kernel(
    alpha: wp.array(dtype=float, ndim=3),
    rays: wp.array(dtype=wp.vec3, ndim=3),
    viewmats: wp.array(dtype=wp.mat44),
    cameras: wp.array(dtype=Camera),
    coeffs: wp.array(dtype=wp.vec3),
    grad_out: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] dL/dC_out
    grad_alpha: wp.array(dtype=float, ndim=3),  # [C,H,W] out
    grad_coeffs: wp.array(dtype=wp.vec3, ndim=2),  # [C*H, 16] out: per image row (few atomics), summed after
):
    c, y, x = wp.tid()
    ray = rays[c, y, x]
    if not has_background(cameras[c], ray, y, x):
        grad_alpha[c, y, x] = 0.0
        return
    b = sh_basis(world_direction(ray, viewmats[c]))
    g = grad_out[c, y, x]
    bg = wp.vec3(0.0)
    for k in range(16):
        bg += b[k] * coeffs[k]
    grad_alpha[c, y, x] = -wp.dot(g, bg)
    t = 1.0 - alpha[c, y, x]
    row = c * alpha.shape[1] + y
    for k in range(16):
        wp.atomic_add(grad_coeffs, row, k, (t * b[k]) * g)


@wp.kernel(enable_backward=False)
def sum_rows_kernel(rows: wp.array(dtype=wp.vec3, ndim=2), total: wp.array(dtype=wp.vec3)):
    r, k = wp.tid()
    wp.atomic_add(total, k, rows[r, k])


def composite(color: wp.array, alpha: wp.array, rays: wp.array, viewmats: wp.array, cameras: wp.array, coeffs: wp.array, out: wp.array | None = None) -> wp.array:
    """``color + (1 - alpha) B(d)`` [C,H,W] vec3 (see the module docstring)."""
    if out is None:
        out = wp.empty_like(color)
    wp.launch(composite_kernel, dim=color.shape, inputs=[color, alpha, rays, viewmats, cameras, coeffs], outputs=[out], device=color.device)
    return out


def composite_backward(alpha: wp.array, rays: wp.array, viewmats: wp.array, cameras: wp.array, coeffs: wp.array, grad_out: wp.array) -> tuple[wp.array, wp.array]:
    """``(dL/dalpha [C,H,W], dL/dcoeffs [16] vec3)`` from ``dL/dC_out`` [C,H,W]; the
    gradient w.r.t. the splats' colour is ``grad_out`` itself."""
    C, H, W = alpha.shape
    dev = alpha.device
    grad_alpha = wp.empty((C, H, W), dtype=float, device=dev)
    rows = wp.zeros((C * H, N_COEFFS), dtype=wp.vec3, device=dev)
    wp.launch(composite_backward_kernel, dim=(C, H, W), inputs=[alpha, rays, viewmats, cameras, coeffs, grad_out], outputs=[grad_alpha, rows], device=dev)
    grad_coeffs = wp.zeros(N_COEFFS, dtype=wp.vec3, device=dev)
    wp.launch(sum_rows_kernel, dim=(C * H, N_COEFFS), inputs=[rows], outputs=[grad_coeffs], device=dev)
    return grad_alpha, grad_coeffs
