"""Multi-camera bundle adjustment (MCBA) kernels: per-pixel reprojection residuals,
their Jacobians, and the reduction into the blocks of the Schur system (paper eq. 6-10).

An edge ``(i, ci, j, cj)`` links keyframe i seen by camera ci to keyframe j seen by
camera cj. For a pixel ``p`` of (i, ci) with inverse depth ``d`` and unit-depth ray
``ray(p)`` (``camera_unproject(cam, p, 1)``):

    X_ci = ray(p) / d
    X_cj = inv(T_b_cj) @ inv(T_w_bj) @ T_w_bi @ T_b_ci @ X_ci        (DESIGN.md)
    r    = target(p) - project_cj(X_cj)                              (pixels)

Poses are perturbed on the right in the body frame, ``T_w_b <- T_w_b @ Exp(xi)``,
``xi = (rho, phi)``; ``J = d project / d x`` (so the Gauss-Newton step solves
``J^T W J dx = J^T W r``). With ``W = w * huber(|r| sqrt(w))`` per pixel the kernel
accumulates, for each edge, the pose blocks ``H_ii, H_ij, H_jj`` and gradients
``v_i, v_j``; per pixel, the pose-depth couplings ``E_i, E_j`` (written per edge),
and per depth variable of (i, ci) the diagonal ``C`` and gradient ``w``.
When ``i == j`` (a cross-view edge, eq. 8) the rig pose cancels: only depth terms.
"""

from __future__ import annotations

import warp as wp

from .camera import FAR, NEAR, Camera, camera_in_domain, camera_jacobian, camera_project, camera_unproject
from .se3 import skew, vec6

wp.set_module_options({"enable_backward": False})

mat66 = wp.types.matrix(shape=(6, 6), dtype=wp.float32)
mat26 = wp.types.matrix(shape=(2, 6), dtype=wp.float32)

#: Residuals whose predicted pixel lies further than this outside the image are dropped (px).
IMAGE_MARGIN = wp.constant(1.0)


@wp.kernel
def grid_rays_kernel(cameras: wp.array(dtype=Camera), rays: wp.array(dtype=wp.vec3, ndim=3)):
    """Unit-depth rays of every pixel of each (reduced) camera: [C,h,w]."""
    c, y, x = wp.tid()
    cam = cameras[c]
    if x < cam.width and y < cam.height:
        rays[c, y, x] = camera_unproject(cam, wp.vec2(float(x), float(y)), 1.0)


@wp.kernel
def unproject_points_kernel(cam: Camera, uv: wp.array(dtype=wp.vec2), rays: wp.array(dtype=wp.vec3)):
    """Unit-depth rays of arbitrary pixels ``uv`` [M] of one camera."""
    i = wp.tid()
    rays[i] = camera_unproject(cam, uv[i], 1.0)


@wp.func
def edge_geometry(
    ray: wp.vec3,
    d: float,
    T_w_bi: wp.transform,
    T_w_bj: wp.transform,
    T_b_ci: wp.transform,
    T_b_cj: wp.transform,
):
    """Points along the edge: ``X_ci``, ``X_bi`` (body i), ``X_bj`` (body j), ``X_cj``."""
    X_ci = ray / d
    X_bi = wp.transform_point(T_b_ci, X_ci)
    X_w = wp.transform_point(T_w_bi, X_bi)
    X_bj = wp.transform_point(wp.transform_inverse(T_w_bj), X_w)
    X_cj = wp.transform_point(wp.transform_inverse(T_b_cj), X_bj)
    return X_ci, X_bi, X_bj, X_cj


@wp.func
def huber_weight(s: float, delta: float):
    if s <= delta:
        return 1.0
    return delta / s


@wp.func
def huber_cost(s: float, delta: float):
    if s <= delta:
        return 0.5 * s * s
    return delta * (s - 0.5 * delta)


@wp.func
def residual_weight(wgt: float, target: wp.vec2):
    """Confidence of one residual: 0 where the weight or the target is not finite, so a
    NaN/Inf correspondence drops out of the cost and the normal equations alike."""
    if wp.isfinite(wgt) and wp.isfinite(target):
        return wgt
    return 0.0


@wp.func
def residual_valid(cam: Camera, X: wp.vec3, uv: wp.vec2):
    if not camera_in_domain(cam, X, NEAR, FAR):
        return False
    m = IMAGE_MARGIN
    return uv[0] >= -m and uv[1] >= -m and uv[0] <= float(cam.width - 1) + m and uv[1] <= float(cam.height - 1) + m


@wp.kernel
def mcba_linearize_kernel(
    rays: wp.array(dtype=wp.vec3, ndim=3),  # [C,h,w] unit-depth rays
    disp: wp.array(dtype=float, ndim=4),  # [K,C,h,w] inverse depth, 1/m
    poses: wp.array(dtype=wp.transform),  # [K] T_w_b
    T_b_c: wp.array(dtype=wp.transform),  # [C]
    cameras: wp.array(dtype=Camera),  # [C] at the reduced resolution
    edges: wp.array(dtype=wp.vec4i),  # [E] (i, ci, j, cj)
    targets: wp.array(dtype=wp.vec2, ndim=3),  # [E,h,w] corresponding pixel in (j, cj)
    weights: wp.array(dtype=float, ndim=3),  # [E,h,w] confidence >= 0 (NaN/Inf target or weight: 0)
    huber_delta: float,  # px
    H: wp.array(dtype=mat66, ndim=2),  # [E,3] out: H_ii, H_ij, H_jj
    g: wp.array(dtype=vec6, ndim=2),  # [E,2] out: v_i, v_j
    Epix: wp.array(dtype=vec6, ndim=4),  # [E,h,w,2] out: E_i, E_j per pixel
    C: wp.array(dtype=float, ndim=4),  # [K,C,h,w] out (accumulated)
    wdepth: wp.array(dtype=float, ndim=4),  # [K,C,h,w] out (accumulated)
    cost: wp.array(dtype=float),  # [E] out (accumulated robust cost)
):
    e, y, x = wp.tid()
    edge = edges[e]
    i = edge[0]
    ci = edge[1]
    j = edge[2]
    cj = edge[3]
    cam_i = cameras[ci]
    if x >= cam_i.width or y >= cam_i.height:
        return
    target = targets[e, y, x]
    wgt = residual_weight(weights[e, y, x], target)
    d = disp[i, ci, y, x]
    if wgt <= 0.0 or d <= 0.0:
        return
    cam_j = cameras[cj]
    X_ci, X_bi, X_bj, X_cj = edge_geometry(rays[ci, y, x], d, poses[i], poses[j], T_b_c[ci], T_b_c[cj])
    uv = camera_project(cam_j, X_cj)
    if not residual_valid(cam_j, X_cj, uv):
        return
    r = target - uv
    s = wp.sqrt(wgt) * wp.length(r)
    W = wgt * huber_weight(s, huber_delta)
    wp.atomic_add(cost, e, huber_cost(s, huber_delta))

    Jp = camera_jacobian(cam_j, X_cj)  # 2x3
    R_cj_bj = wp.quat_to_matrix(wp.quat_inverse(wp.transform_get_rotation(T_b_c[cj])))
    R_bj_w = wp.quat_to_matrix(wp.quat_inverse(wp.transform_get_rotation(poses[j])))
    R_w_bi = wp.quat_to_matrix(wp.transform_get_rotation(poses[i]))
    R_bi_ci = wp.quat_to_matrix(wp.transform_get_rotation(T_b_c[ci]))
    A_j = Jp * R_cj_bj  # d uv / d X_bj
    A_i = A_j * R_bj_w * R_w_bi  # d uv / d X_bi
    # depth: X_ci = ray / d  ->  dX_ci/dd = -X_ci / d
    Jd = (A_i * R_bi_ci) * (-X_ci / d)  # 2-vector

    wp.atomic_add(C, i, ci, y, x, W * wp.dot(Jd, Jd))
    wp.atomic_add(wdepth, i, ci, y, x, W * wp.dot(Jd, r))
    if i == j:
        return  # cross-view edge at one timestamp: the rig pose cancels (eq. 8)

    # pose i: X_bi <- Exp(xi) X_bi = X_bi + rho + phi x X_bi  ->  [I, -skew(X_bi)]
    Si = -skew(X_bi)
    # pose j: X_bj <- Exp(-xi) X_bj = X_bj - rho - phi x X_bj  ->  [-I, skew(X_bj)]
    Sj = skew(X_bj)
    Ji = mat26()
    Jj = mat26()
    ARi = A_i * Si
    ARj = A_j * Sj
    for a in range(2):
        for k in range(3):
            Ji[a, k] = A_i[a, k]
            Ji[a, k + 3] = ARi[a, k]
            Jj[a, k] = -A_j[a, k]
            Jj[a, k + 3] = ARj[a, k]
    JiT = wp.transpose(Ji)
    JjT = wp.transpose(Jj)
    wp.atomic_add(H, e, 0, W * (JiT * Ji))
    wp.atomic_add(H, e, 1, W * (JiT * Jj))
    wp.atomic_add(H, e, 2, W * (JjT * Jj))
    wp.atomic_add(g, e, 0, W * (JiT * r))
    wp.atomic_add(g, e, 1, W * (JjT * r))
    Epix[e, y, x, 0] = W * (JiT * Jd)
    Epix[e, y, x, 1] = W * (JjT * Jd)


@wp.kernel
def mcba_cost_kernel(
    rays: wp.array(dtype=wp.vec3, ndim=3),
    disp: wp.array(dtype=float, ndim=4),
    poses: wp.array(dtype=wp.transform),
    T_b_c: wp.array(dtype=wp.transform),
    cameras: wp.array(dtype=Camera),
    edges: wp.array(dtype=wp.vec4i),
    targets: wp.array(dtype=wp.vec2, ndim=3),
    weights: wp.array(dtype=float, ndim=3),
    huber_delta: float,
    cost: wp.array(dtype=float),  # [E] out (accumulated)
):
    """Robust cost only (for accepting or rejecting an LM step)."""
    e, y, x = wp.tid()
    edge = edges[e]
    cam_i = cameras[edge[1]]
    if x >= cam_i.width or y >= cam_i.height:
        return
    target = targets[e, y, x]
    wgt = residual_weight(weights[e, y, x], target)
    d = disp[edge[0], edge[1], y, x]
    if wgt <= 0.0 or d <= 0.0:
        return
    cam_j = cameras[edge[3]]
    X_ci, X_bi, X_bj, X_cj = edge_geometry(rays[edge[1], y, x], d, poses[edge[0]], poses[edge[2]], T_b_c[edge[1]], T_b_c[edge[3]])
    uv = camera_project(cam_j, X_cj)
    if not residual_valid(cam_j, X_cj, uv):
        return
    r = target - uv
    wp.atomic_add(cost, e, huber_cost(wp.sqrt(wgt) * wp.length(r), huber_delta))
