"""Kernels of the mapping stage: Adam, pose-consistent moves, regularizers, the keyframe
views and pose corrections, densification statistics and the finiteness guard."""

from __future__ import annotations

import warp as wp

from .camera import FAR, NEAR, Camera, camera_in_domain, camera_project
from .se3 import mat66, se3_retract, vec6

wp.set_module_options({"enable_backward": False})


@wp.kernel
def adam_kernel(
    param: wp.array(dtype=float),  # flat view of a parameter array
    grad: wp.array(dtype=float),
    m: wp.array(dtype=float),
    v: wp.array(dtype=float),
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    bias1: float,  # 1 - beta1^t
    bias2: float,  # 1 - beta2^t
):
    """One Adam step on a flat parameter array (Gaussians, exposures, pose corrections)."""
    i = wp.tid()
    g = grad[i]
    mi = beta1 * m[i] + (1.0 - beta1) * g
    vi = beta2 * v[i] + (1.0 - beta2) * g * g
    m[i] = mi
    v[i] = vi
    param[i] = param[i] - lr * (mi / bias1) / (wp.sqrt(vi / bias2) + eps)


@wp.kernel
def move_anchored_kernel(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),  # (x, y, z, w)
    log_scales: wp.array(dtype=wp.vec3),
    anchors: wp.array(dtype=wp.int32),
    keyframe: int,
    delta: wp.mat44,  # world-frame correction: x <- delta x
    log_scale_change: float,  # log of the scale factor s_t (eq. 13), 0 for none
):
    """Eq. 12-13: Gaussians anchored to ``keyframe`` follow its pose change rigidly."""
    i = wp.tid()
    if anchors[i] != keyframe:
        return
    R = wp.mat33(delta[0, 0], delta[0, 1], delta[0, 2], delta[1, 0], delta[1, 1], delta[1, 2], delta[2, 0], delta[2, 1], delta[2, 2])
    t = wp.vec3(delta[0, 3], delta[1, 3], delta[2, 3])
    means[i] = R * means[i] + t
    q = quats[i]
    qr = wp.quat_from_matrix(R) * wp.quat(q[0], q[1], q[2], q[3])
    quats[i] = wp.vec4(qr[0], qr[1], qr[2], qr[3])
    log_scales[i] = log_scales[i] + wp.vec3(log_scale_change)


@wp.func
def sample_grid(grid: wp.array(dtype=float, ndim=3), c: int, u: float, v: float, width: int, height: int):
    """Bilinear sample of ``grid[c]`` at continuous pixel ``(u, v)`` inside ``[0, w-1] x [0, h-1]``."""
    x0 = wp.clamp(int(wp.floor(u)), 0, wp.max(width - 2, 0))
    y0 = wp.clamp(int(wp.floor(v)), 0, wp.max(height - 2, 0))
    x1 = wp.min(x0 + 1, width - 1)
    y1 = wp.min(y0 + 1, height - 1)
    fx = u - float(x0)
    fy = v - float(y0)
    a = grid[c, y0, x0] * (1.0 - fx) + grid[c, y0, x1] * fx
    b = grid[c, y1, x0] * (1.0 - fx) + grid[c, y1, x1] * fx
    return a * (1.0 - fy) + b * fy


@wp.kernel
def follow_depth_kernel(
    means: wp.array(dtype=wp.vec3),
    log_scales: wp.array(dtype=wp.vec3),
    anchors: wp.array(dtype=wp.int32),
    keyframe: int,
    T_c_w: wp.array(dtype=wp.transform),  # [C] world -> camera c of the keyframe
    cameras: wp.array(dtype=Camera),  # [C] at the ratio grid's resolution
    ratio: wp.array(dtype=float, ndim=3),  # [C,h,w] new / old depth of the keyframe
):
    """Eq. 13 per pixel: a Gaussian anchored to ``keyframe`` moves along the ray of the
    keyframe camera that sees it nearest its image centre, by that camera's depth ratio at
    its pixel (bilinear), and its size scales alike; a Gaussian no camera sees stays."""
    i = wp.tid()
    if anchors[i] != keyframe:
        return
    X = means[i]
    best = float(1.0e30)
    s = float(1.0)
    centre = wp.vec3(0.0)
    for c in range(cameras.shape[0]):
        cam = cameras[c]
        Xc = wp.transform_point(T_c_w[c], X)
        if not camera_in_domain(cam, Xc, NEAR, FAR):
            continue
        uv = camera_project(cam, Xc)
        w = float(cam.width)
        h = float(cam.height)
        if uv[0] < 0.0 or uv[1] < 0.0 or uv[0] > w - 1.0 or uv[1] > h - 1.0:
            continue
        du = (uv[0] - 0.5 * (w - 1.0)) / w
        dv = (uv[1] - 0.5 * (h - 1.0)) / h
        r2 = du * du + dv * dv
        if r2 < best:
            best = r2
            s = sample_grid(ratio, c, uv[0], uv[1], cam.width, cam.height)
            centre = wp.transform_point(wp.transform_inverse(T_c_w[c]), wp.vec3(0.0))
    if best < 1.0e30 and s > 0.0:
        means[i] = centre + s * (X - centre)
        log_scales[i] = log_scales[i] + wp.vec3(wp.log(s))


@wp.kernel
def isotropy_loss_kernel(
    log_scales: wp.array(dtype=wp.vec3),
    weight: float,
    loss: wp.array(dtype=float),  # [1] accumulated
    grad: wp.array(dtype=wp.vec3),  # accumulated
):
    """Eq. 11 scale term: ``weight * sum_k |s_k - mean(s)|`` per Gaussian (linear scales)."""
    i = wp.tid()
    ls = log_scales[i]
    s = wp.vec3(wp.exp(ls[0]), wp.exp(ls[1]), wp.exp(ls[2]))
    mean = (s[0] + s[1] + s[2]) / 3.0
    total = float(0.0)
    g = wp.vec3(0.0)
    for k in range(3):
        d = s[k] - mean
        total += wp.abs(d)
        sg = wp.sign(d)
        for a in range(3):  # d|s_k - mean| / d s_a
            coef = -1.0 / 3.0
            if a == k:
                coef = 2.0 / 3.0
            g[a] = g[a] + sg * coef
    wp.atomic_add(loss, 0, weight * total)
    grad[i] = grad[i] + weight * wp.cw_mul(g, s)  # chain rule through exp


SKY_EPS = wp.constant(0.02)  # the sky term's floor on transmittance (1 - alpha)


@wp.kernel(enable_backward=False)
def sky_alpha_loss_kernel(
    alpha: wp.array(dtype=float, ndim=3),  # [C,H,W] rendered
    sky: wp.array(dtype=float, ndim=3),  # [C,H,W] weight per pixel: 1 / (camera's pixels) on sky, else 0
    weight: float,
    loss: wp.array(dtype=float),  # [1] accumulated
    grad_alpha: wp.array(dtype=float, ndim=3),  # [C,H,W] accumulated
):
    """Sky term: ``weight * sum_pixels sky * -log(1 - alpha)``, the binary cross-entropy of the
    rendered alpha against "no Gaussian here" (as outdoor splatting systems' sky-mask loss).
    Unlike a linear term its gradient grows as the splats saturate the pixel (where
    ``d alpha / d opacity`` vanishes); ``1 - alpha`` is floored at ``SKY_EPS``, below which the
    gradient stays at ``weight * sky / SKY_EPS``."""
    c, y, x = wp.tid()
    w = sky[c, y, x]
    if w > 0.0:
        t = wp.max(1.0 - alpha[c, y, x], SKY_EPS)
        wp.atomic_add(loss, 0, -weight * w * wp.log(t))
        grad_alpha[c, y, x] = grad_alpha[c, y, x] + weight * w / t


@wp.kernel
def keyframe_viewmats_kernel(
    poses: wp.array(dtype=wp.transform),  # [K] T_w_b
    T_b_c: wp.array(dtype=wp.transform),  # [C] camera -> body
    keyframe: int,
    viewmats: wp.array(dtype=wp.mat44),  # [C] out: T_c_w of the keyframe's cameras
):
    """World -> camera matrices ``inv(T_w_b @ T_b_c)`` of one keyframe's rig views."""
    c = wp.tid()
    T = wp.transform_inverse(wp.transform_multiply(poses[keyframe], T_b_c[c]))
    R = wp.quat_to_matrix(wp.transform_get_rotation(T))
    t = wp.transform_get_translation(T)
    viewmats[c] = wp.mat44(R[0, 0], R[0, 1], R[0, 2], t[0], R[1, 0], R[1, 1], R[1, 2], t[1], R[2, 0], R[2, 1], R[2, 2], t[2], 0.0, 0.0, 0.0, 1.0)


@wp.kernel
def body_pose_gradient_kernel(
    camera_grads: wp.array(dtype=vec6),  # [C] dL/d xi_c, camera-frame increments
    adjoints_T: wp.array(dtype=mat66),  # [C] Ad(T_c_b)^T
    n_cameras: int,
    grad: wp.array(dtype=float),  # [6] out: dL/d xi_b, body-frame increment
):
    """Camera-pose gradients to the rig body: ``xi_c = Ad(T_c_b) xi_b`` so
    ``dL/d xi_b = sum_c Ad(T_c_b)^T dL/d xi_c`` (launch with dim 1)."""
    g = vec6()
    for c in range(n_cameras):
        g += adjoints_T[c] * camera_grads[c]
    for i in range(6):
        grad[i] = g[i]


@wp.kernel
def retract_pose_kernel(
    poses: wp.array(dtype=wp.transform),  # [K] T_w_b
    keyframe: int,
    xi: wp.array(dtype=float),  # [6] body-frame increment (rho, phi), m and rad
):
    """``T_w_b <- T_w_b @ Exp(xi)`` for one keyframe, rotation renormalized (launch with dim 1)."""
    T = se3_retract(poses[keyframe], vec6(xi[0], xi[1], xi[2], xi[3], xi[4], xi[5]))
    poses[keyframe] = wp.transform(wp.transform_get_translation(T), wp.normalize(wp.transform_get_rotation(T)))


@wp.kernel
def view_gradient_stats_kernel(
    mean2d_grads: wp.array(dtype=wp.vec2),  # [C*N] dL/d projected mean, px^-1
    visible: wp.array(dtype=wp.int32),  # [C*N]
    n_gaussians: int,
    n_views: int,
    accum: wp.array(dtype=wp.float64),  # [N] accumulated sum over views of |dL/d mean2d|
    count: wp.array(dtype=wp.float64),  # [N] accumulated number of views that saw the Gaussian
):
    """Densification statistics of one step (one thread per Gaussian, deterministic)."""
    i = wp.tid()
    s = float(0.0)
    k = int(0)
    for c in range(n_views):
        j = c * n_gaussians + i
        s += wp.length(mean2d_grads[j])
        if visible[j] > 0:
            k += 1
    accum[i] = accum[i] + wp.float64(s)
    count[i] = count[i] + wp.float64(k)


@wp.kernel
def count_nonfinite_kernel(values: wp.array(dtype=float), count: wp.array(dtype=wp.int32)):
    """``count[0] += #`` NaN or Inf entries of a flat array."""
    i = wp.tid()
    if not wp.isfinite(values[i]):
        wp.atomic_add(count, 0, 1)
