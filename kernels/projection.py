"""EWA projection of 3D Gaussians into a batch of cameras, and its adjoint.

One thread per (camera, Gaussian) pair, ``flat = c * N + i``.

Forward (3DGS reference conventions, DESIGN.md "Gaussians and splatting"):

* ``p_c = R_c_w p_w + t_c_w``; culled unless the camera model's depth lies in
  ``[near, far]`` and ``p_c`` is inside the model's valid domain.
* ``Sigma = R S S^T R^T`` from the normalized quaternion ``(x, y, z, w)`` and
  ``S = diag(exp(log_scale))``; ``Sigma' = J W Sigma W^T J^T + 0.3 I`` with
  ``J`` the camera model's 2x3 Jacobian at ``p_c`` and ``W = R_c_w``.
* Culled when the 2D mean lies more than one image size outside the image
  (``u`` outside ``[-W, 2W]`` or ``v`` outside ``[-H, 2H]``): such a splat can only
  reach the image with a huge, badly approximated footprint (gsplat clamps the
  Jacobian for the same reason), and its covariance overflows float32 gradients.
* Outputs the 2D mean (pixels), the conic ``(a, b, c)`` of ``inv(Sigma')``, the
  Gaussian's depth (``z`` or ray length), and its opacity ``sigmoid(logit)``.
  Gaussians with opacity below 1/255 can touch no pixel and are culled here.

Backward: gradients of the loss w.r.t. the 2D outputs are carried to the means,
quaternions, log-scales and opacity logits, and to each camera's pose as a
6-vector ``(rho, phi)`` for the right-multiplied increment
``T_w_c <- T_w_c @ Exp(xi)`` (camera frame; ODGS supplementary S1.2, here with
the covariance path included so the gradient is exact).
"""

from __future__ import annotations

import warp as wp

from .camera import Camera, camera_depth, camera_depth_grad, camera_in_domain, camera_jacobian, camera_jacobian_vjp, camera_project
from .se3 import vec6

#: Added to the diagonal of every 2D covariance (px^2), as the 3DGS reference.
COV2D_BLUR = wp.constant(0.3)
#: Smallest alpha that counts as a contribution.
ALPHA_MIN = wp.constant(1.0 / 255.0)


@wp.func
def quat_to_rotation(q: wp.vec4):
    """Rotation matrix of quaternion ``q = (x, y, z, w)`` after normalization."""
    qn = wp.normalize(q)
    return wp.quat_to_matrix(wp.quat(qn[0], qn[1], qn[2], qn[3]))


@wp.func
def view_rotation(V: wp.mat44):
    return wp.mat33(V[0, 0], V[0, 1], V[0, 2], V[1, 0], V[1, 1], V[1, 2], V[2, 0], V[2, 1], V[2, 2])


@wp.func
def view_translation(V: wp.mat44):
    return wp.vec3(V[0, 3], V[1, 3], V[2, 3])


@wp.kernel
def project_gaussians_kernel(
    means: wp.array(dtype=wp.vec3),  # [N] world, m
    quats: wp.array(dtype=wp.vec4),  # [N] (x, y, z, w), any norm
    log_scales: wp.array(dtype=wp.vec3),  # [N] log(m)
    opacity_logits: wp.array(dtype=float),  # [N]
    cameras: wp.array(dtype=Camera),  # [C]
    viewmats: wp.array(dtype=wp.mat44),  # [C] T_c_w, world -> camera
    n_gaussians: int,
    near: float,
    far: float,
    mean2d: wp.array(dtype=wp.vec2),  # [C*N] pixels
    conic: wp.array(dtype=wp.vec3),  # [C*N] inv(Sigma') as (a, b, c)
    depth: wp.array(dtype=float),  # [C*N] m
    opacity: wp.array(dtype=float),  # [C*N] in (0, 1)
    visible: wp.array(dtype=wp.int32),  # [C*N] 1 if not culled
):
    flat = wp.tid()
    c = flat // n_gaussians
    i = flat - c * n_gaussians
    cam = cameras[c]
    V = viewmats[c]
    W = view_rotation(V)
    pc = W * means[i] + view_translation(V)
    if not camera_in_domain(cam, pc, near, far):
        visible[flat] = 0
        return
    o = 1.0 / (1.0 + wp.exp(-opacity_logits[i]))
    if o < ALPHA_MIN:
        visible[flat] = 0
        return
    uv = camera_project(cam, pc)
    w = float(cam.width)
    h = float(cam.height)
    if not (uv[0] >= -w and uv[0] <= 2.0 * w and uv[1] >= -h and uv[1] <= 2.0 * h):
        visible[flat] = 0
        return
    Rg = quat_to_rotation(quats[i])
    s = log_scales[i]
    Ms = Rg * wp.diag(wp.vec3(wp.exp(s[0]), wp.exp(s[1]), wp.exp(s[2])))
    cov = Ms * wp.transpose(Ms)
    M = camera_jacobian(cam, pc) * W
    S2 = M * cov * wp.transpose(M)
    a = S2[0, 0] + COV2D_BLUR
    b = S2[0, 1]
    cc = S2[1, 1] + COV2D_BLUR
    det = a * cc - b * b
    if not (det > 0.0 and det < 1.0e30):  # also rejects NaN
        visible[flat] = 0
        return
    mean2d[flat] = uv
    conic[flat] = wp.vec3(cc / det, -b / det, a / det)
    depth[flat] = camera_depth(cam, pc)
    opacity[flat] = o
    visible[flat] = 1


@wp.func
def rotation_vjp(qn: wp.vec4, G: wp.mat33):
    """Gradient w.r.t. the unit quaternion ``qn = (x, y, z, w)`` of ``<G, R(qn)>``."""
    x = qn[0]
    y = qn[1]
    z = qn[2]
    w = qn[3]
    gx = 2.0 * (
        y * (G[0, 1] + G[1, 0]) + z * (G[0, 2] + G[2, 0]) - 2.0 * x * (G[1, 1] + G[2, 2]) + w * (G[2, 1] - G[1, 2])
    )
    gy = 2.0 * (
        x * (G[0, 1] + G[1, 0]) + z * (G[1, 2] + G[2, 1]) - 2.0 * y * (G[0, 0] + G[2, 2]) + w * (G[0, 2] - G[2, 0])
    )
    gz = 2.0 * (
        x * (G[0, 2] + G[2, 0]) + y * (G[1, 2] + G[2, 1]) - 2.0 * z * (G[0, 0] + G[1, 1]) + w * (G[1, 0] - G[0, 1])
    )
    gw = 2.0 * (x * (G[2, 1] - G[1, 2]) + y * (G[0, 2] - G[2, 0]) + z * (G[1, 0] - G[0, 1]))
    return wp.vec4(gx, gy, gz, gw)


@wp.kernel
def project_gaussians_backward_kernel(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    log_scales: wp.array(dtype=wp.vec3),
    opacity_logits: wp.array(dtype=float),
    cameras: wp.array(dtype=Camera),
    viewmats: wp.array(dtype=wp.mat44),
    n_gaussians: int,
    visible: wp.array(dtype=wp.int32),  # [C*N] from the forward pass
    opacity: wp.array(dtype=float),  # [C*N] from the forward pass
    grad_mean2d: wp.array(dtype=wp.vec2),  # [C*N] dL/d mean2d
    grad_conic: wp.array(dtype=wp.vec3),  # [C*N] dL/d (a, b, c)
    grad_depth: wp.array(dtype=float),  # [C*N] dL/d depth
    grad_opacity: wp.array(dtype=float),  # [C*N] dL/d opacity
    grad_means: wp.array(dtype=wp.vec3),  # [N] accumulated over cameras
    grad_quats: wp.array(dtype=wp.vec4),  # [N]
    grad_log_scales: wp.array(dtype=wp.vec3),  # [N]
    grad_opacity_logits: wp.array(dtype=float),  # [N]
    grad_pose: wp.array(dtype=vec6),  # [C] dL/d xi, T_w_c <- T_w_c Exp(xi)
):
    flat = wp.tid()
    if visible[flat] == 0:
        return
    c = flat // n_gaussians
    i = flat - c * n_gaussians
    cam = cameras[c]
    V = viewmats[c]
    W = view_rotation(V)
    pc = W * means[i] + view_translation(V)

    # Recompute the forward quantities.
    q = quats[i]
    qnorm = wp.length(q)
    qn = q / qnorm
    Rg = wp.quat_to_matrix(wp.quat(qn[0], qn[1], qn[2], qn[3]))
    ls = log_scales[i]
    sv = wp.vec3(wp.exp(ls[0]), wp.exp(ls[1]), wp.exp(ls[2]))
    Ms = Rg * wp.diag(sv)
    cov = Ms * wp.transpose(Ms)
    J = camera_jacobian(cam, pc)
    M = J * W
    S2 = M * cov * wp.transpose(M)
    a = S2[0, 0] + COV2D_BLUR
    b = S2[0, 1]
    cc = S2[1, 1] + COV2D_BLUR
    det = a * cc - b * b

    # conic (qa, qb, qc) = (cc, -b, a) / det  ->  gradients on (a, b, cc).
    gq = grad_conic[flat]
    id2 = 1.0 / (det * det)
    ga = -gq[0] * cc * cc * id2 + gq[1] * b * cc * id2 + gq[2] * (1.0 / det - a * cc * id2)
    gc = gq[0] * (1.0 / det - a * cc * id2) + gq[1] * a * b * id2 - gq[2] * a * a * id2
    gb = 2.0 * b * id2 * (gq[0] * cc + gq[2] * a) - gq[1] * (1.0 / det + 2.0 * b * b * id2)
    Gs = wp.mat22(ga, 0.5 * gb, 0.5 * gb, gc)  # dL/dSigma' (symmetric)

    gM = 2.0 * (Gs * M * cov)  # 2x3
    gcov = wp.transpose(M) * Gs * M  # 3x3
    gJ = gM * wp.transpose(W)
    gW = wp.transpose(J) * gM

    # Sigma = Ms Ms^T, Ms = R diag(s)
    gMs = 2.0 * (gcov * Ms)
    gR = gMs * wp.diag(sv)
    gls = wp.vec3(
        (gMs[0, 0] * Rg[0, 0] + gMs[1, 0] * Rg[1, 0] + gMs[2, 0] * Rg[2, 0]) * sv[0],
        (gMs[0, 1] * Rg[0, 1] + gMs[1, 1] * Rg[1, 1] + gMs[2, 1] * Rg[2, 1]) * sv[1],
        (gMs[0, 2] * Rg[0, 2] + gMs[1, 2] * Rg[1, 2] + gMs[2, 2] * Rg[2, 2]) * sv[2],
    )
    gqn = rotation_vjp(qn, gR)
    gq4 = (gqn - wp.dot(gqn, qn) * qn) / qnorm

    # Camera-frame point: through the 2D mean, the depth and the Jacobian.
    gpc = wp.transpose(J) * grad_mean2d[flat]
    gpc += grad_depth[flat] * camera_depth_grad(cam, pc)
    gpc += camera_jacobian_vjp(cam, pc, gJ)

    wp.atomic_add(grad_means, i, wp.transpose(W) * gpc)
    wp.atomic_add(grad_quats, i, gq4)
    wp.atomic_add(grad_log_scales, i, gls)
    o = opacity[flat]
    wp.atomic_add(grad_opacity_logits, i, grad_opacity[flat] * o * (1.0 - o))

    # Pose: p_c <- p_c - rho - phi x p_c,  W <- W - skew(phi) W.
    gphi = wp.cross(gpc, pc)
    A = gW * wp.transpose(W)
    gphi -= wp.vec3(A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1])
    wp.atomic_add(grad_pose, c, vec6(-gpc[0], -gpc[1], -gpc[2], gphi[0], gphi[1], gphi[2]))
