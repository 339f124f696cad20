"""Per-Gaussian kernels of the mapping stage: Adam, pose-consistent moves, regularizers."""

from __future__ import annotations

import warp as wp

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


@wp.kernel
def scale_anchored_kernel(
    means: wp.array(dtype=wp.vec3),
    log_scales: wp.array(dtype=wp.vec3),
    anchors: wp.array(dtype=wp.int32),
    keyframe: int,
    centre: wp.vec3,  # world position the scale change is about (the keyframe's rig origin)
    scale: float,
):
    """Eq. 13: Gaussians anchored to ``keyframe`` follow a depth-scale change ``s`` of
    that keyframe: positions move along their rays from ``centre``, sizes scale by ``s``."""
    i = wp.tid()
    if anchors[i] != keyframe:
        return
    means[i] = centre + scale * (means[i] - centre)
    log_scales[i] = log_scales[i] + wp.vec3(wp.log(scale))


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
