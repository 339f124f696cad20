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

The Schur complement (eq. 10) is reduced sparsely here too (``schur_pairs_kernel``,
``schur_rhs_kernel``, added into the 6n x 6n reduced camera system by
``schur_scatter_kernel`` and ``pose_system_kernel``), followed by the back-substitution and the candidate state of a
Levenberg-Marquardt step (``backsub_coupling_kernel``, ``depth_candidate_kernel``,
``pose_candidate_kernel``), the optional inverse-depth prior, and the costs; those
kernels index depths and poses by window slot (``window_copy_kernel``).
"""

from __future__ import annotations

import warp as wp

from .camera import FAR, NEAR, Camera, camera_in_domain, camera_jacobian, camera_project, camera_unproject, mat23
from .se3 import se3_adjoint, se3_retract, skew, vec6

wp.set_module_options({"enable_backward": False})

mat66 = wp.types.matrix(shape=(6, 6), dtype=wp.float32)
# Per-edge and per-pair sums over many pixels are accumulated in float64: on CUDA the
# order of atomic additions varies between runs, and float32 sums would then differ by
# ~1e-5 relative (and S would not be exactly symmetric).
mat66d = wp.types.matrix(shape=(6, 6), dtype=wp.float64)
vec6d = wp.types.vector(length=6, dtype=wp.float64)
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


@wp.kernel
def project_points_kernel(
    cam: Camera,
    X: wp.array(dtype=wp.vec3),  # [M] camera-frame points (m)
    near: float,
    far: float,
    uv: wp.array(dtype=wp.vec2),  # [M] pixels (0 where not ok)
    J: wp.array(dtype=mat23),  # [M] d uv / d X (0 where not ok)
    ok: wp.array(dtype=wp.int32),  # [M] 1: finite, inside the near/far range and the model's domain
):
    """Pixels and analytic Jacobians of arbitrary camera-frame points ``X`` [M] of one camera."""
    i = wp.tid()
    p = X[i]
    good = int(0)
    if wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2]):
        if camera_in_domain(cam, p, near, far):
            q = camera_project(cam, p)
            if wp.isfinite(q[0]) and wp.isfinite(q[1]):
                good = 1
                uv[i] = q
                J[i] = camera_jacobian(cam, p)
    ok[i] = good


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
    row0: int,  # first grid row of this launch (a band of rows: see mcgs_warp.kernels.launch)
    H: wp.array(dtype=mat66d, ndim=2),  # [E,3] out (accumulated, float64): H_ii, H_ij, H_jj
    g: wp.array(dtype=vec6d, ndim=2),  # [E,2] out (accumulated, float64): v_i, v_j
    Epix: wp.array(dtype=vec6, ndim=3),  # [E,h,w] out: E_j per pixel (E_i = -Ad^T E_j, edge_adjoint)
    C: wp.array(dtype=float, ndim=4),  # [K,C,h,w] out (accumulated)
    wdepth: wp.array(dtype=float, ndim=4),  # [K,C,h,w] out (accumulated)
    cost: wp.array(dtype=float),  # [E] out (accumulated robust cost)
):
    e, y, x = wp.tid()
    y = y + row0
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
    wp.atomic_add(H, e, 0, mat66d(W * (JiT * Ji)))
    wp.atomic_add(H, e, 1, mat66d(W * (JiT * Jj)))
    wp.atomic_add(H, e, 2, mat66d(W * (JjT * Jj)))
    wp.atomic_add(g, e, 0, vec6d(W * (JiT * r)))
    wp.atomic_add(g, e, 1, vec6d(W * (JjT * r)))
    Epix[e, y, x] = W * (JjT * Jd)  # W JiT Jd = -Ad^T (W JjT Jd): the edge's adjoint, not a second array


@wp.func
def pixel_residual(
    rays: wp.array(dtype=wp.vec3, ndim=3),
    disp: wp.array(dtype=float, ndim=4),
    poses: wp.array(dtype=wp.transform),
    T_b_c: wp.array(dtype=wp.transform),
    cameras: wp.array(dtype=Camera),
    edge: wp.vec4i,
    targets: wp.array(dtype=wp.vec2, ndim=3),
    weights: wp.array(dtype=float, ndim=3),
    e: int,
    y: int,
    x: int,
):
    """Whether grid pixel (y, x) of edge ``e`` has a residual, its confidence and its residual
    ``target - uv`` (grid px): the rule :func:`mcba_linearize_kernel` applies too."""
    zero = wp.vec2(0.0, 0.0)
    cam_i = cameras[edge[1]]
    if x >= cam_i.width or y >= cam_i.height:
        return False, 0.0, zero
    target = targets[e, y, x]
    wgt = residual_weight(weights[e, y, x], target)
    d = disp[edge[0], edge[1], y, x]
    if wgt <= 0.0 or d <= 0.0:
        return False, 0.0, zero
    cam_j = cameras[edge[3]]
    X_ci, X_bi, X_bj, X_cj = edge_geometry(rays[edge[1], y, x], d, poses[edge[0]], poses[edge[2]], T_b_c[edge[1]], T_b_c[edge[3]])
    uv = camera_project(cam_j, X_cj)
    if not residual_valid(cam_j, X_cj, uv):
        return False, 0.0, zero
    return True, wgt, target - uv


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
    row0: int,  # first grid row of this launch
    cost: wp.array(dtype=float),  # [E] out (accumulated)
):
    """Robust cost only (for accepting or rejecting an LM step)."""
    e, y, x = wp.tid()
    ok, wgt, r = pixel_residual(rays, disp, poses, T_b_c, cameras, edges[e], targets, weights, e, y + row0, x)
    if ok:
        wp.atomic_add(cost, e, huber_cost(wp.sqrt(wgt) * wp.length(r), huber_delta))


@wp.kernel
def mcba_residual_kernel(
    rays: wp.array(dtype=wp.vec3, ndim=3),
    disp: wp.array(dtype=float, ndim=4),
    poses: wp.array(dtype=wp.transform),
    T_b_c: wp.array(dtype=wp.transform),
    cameras: wp.array(dtype=Camera),
    edges: wp.array(dtype=wp.vec4i),
    targets: wp.array(dtype=wp.vec2, ndim=3),
    weights: wp.array(dtype=float, ndim=3),
    row0: int,  # first grid row of this launch
    residual: wp.array(dtype=wp.vec2, ndim=3),  # [E,h,w] out: whitened residual sqrt(w) (target - uv), grid px
    valid: wp.array(dtype=wp.int32, ndim=3),  # [E,h,w] out: 1 where the residual counts in the cost
):
    """Per-pixel whitened residuals of the dense class (its noise and correlation are
    estimated from them: ``mcgs_warp.ba.variance``); ``valid`` is 1 exactly where the cost
    kernel counts the pixel."""
    e, y, x = wp.tid()
    y = y + row0
    ok, wgt, r = pixel_residual(rays, disp, poses, T_b_c, cameras, edges[e], targets, weights, e, y, x)
    valid[e, y, x] = wp.where(ok, 1, 0)
    residual[e, y, x] = wp.sqrt(wgt) * r


@wp.func
def edge_adjoint(T_w_bi: wp.transform, T_w_bj: wp.transform):
    """Adjoint ``Ad = [[R, [t]x R], [0, R]]`` of ``T_bj_bi = (R, t)``: a residual's Jacobian
    w.r.t. pose i is ``J_i = -J_j Ad`` (mcba_linearize_kernel's parametrization: ``X_bj = R
    X_bi + t``, so ``A_j R [I, -[X_bi]x] = A_j [I, -[X_bj]x] Ad``), hence every pose-depth
    coupling of pose i follows from pose j's: ``E_i = -Ad^T E_j``."""
    return se3_adjoint(wp.transform_multiply(wp.transform_inverse(T_w_bj), T_w_bi))


@wp.kernel
def edge_adjoint_kernel(
    poses: wp.array(dtype=wp.transform),  # [n] T_w_b, slot-indexed
    edges: wp.array(dtype=wp.vec4i),  # [E] (slot i, ci, slot j, cj)
    Ad: wp.array(dtype=mat66),  # [E] out: edge_adjoint of each edge
):
    e = wp.tid()
    Ad[e] = edge_adjoint(poses[edges[e][0]], poses[edges[e][2]])


# ---------------------------------------------------------------------------------------
# Sparse Schur reduction (paper eq. 10) over a window of n keyframes held in slots 0..n-1.
#
# The depth variable of pixel p of view (i, ci) couples to pose j_e through every edge e
# leaving (i, ci) (``E_{e,j}(p)``, Epix[e, y, x]) and to pose i by ``E_{e,i}(p) = -Ad_e^T
# E_{e,j}(p)`` (:func:`edge_adjoint`: one 6x6 per edge, so only E_j is stored per pixel).
# With ``Q_p = 1 / (C_p (1 + lambda) + lambda DEPTH_DAMPING)`` (0 where C_p == 0) the
# reduced camera system ``S = B - sum_p G_p^T Q_p G_p`` needs, for every ordered pair of
# pose edges (e1, e2) with the same source view, the four 6x6 blocks
# ``sum_p Q_p E_{e1,a}(p) E_{e2,b}(p)^T`` for (a, b) in (i,i), (i,j2), (j1,i), (j1,j2)
# (computed once per unordered pair, e1 <= e2: those of (e2, e1) are their transposes).
# All four follow from ``M = sum_p Q_p E_{e1,j}(p) E_{e2,j}(p)^T`` = (j1,j2):
# (i,i) = Ad1^T M Ad2, (i,j2) = -Ad1^T M, (j1,i) = -M Ad2. The work and memory grow with
# edge pairs x pixels, never with keyframes^2. :func:`schur_pairs_kernel` sums M per
# (pair, image row) in float32 and adds once per row into float64 blocks;
# :func:`schur_pair_blocks_kernel` makes the other three (float64); then the blocks
# (pairs x 4 x 36 numbers) and the per-edge pose blocks B (also float64 sums) are scattered
# into S; only S [6n,6n] and rhs [6n] go to the host for the pose solve.
# ---------------------------------------------------------------------------------------


# Levenberg-Marquardt damping of every inverse depth is ``lambda * (C + DEPTH_DAMPING)``
# (px^2 m^2, the units of C), not ``lambda * C`` alone: that lets a depth which the current
# state barely observes take an arbitrary step. At the first solve of a sequence the new
# keyframe starts at the old pose (zero baseline), every temporal Jacobian w.r.t. depth is
# ~0, and half the depths of the first two keyframes ran to ~1 mm and never came back (RGB
# only: depth L1 of those keyframes 3.2 / 2.1 m with exact correspondences). A well-observed
# depth has C ~ 100 (RGB-only demo median at 00a7bf5), so at the initial lambda (1e-4: an added 1) this changes
# little there, and the term shrinks with lambda as steps are accepted.
DEPTH_DAMPING = wp.constant(1.0e4)


@wp.func
def schur_depth_weight(c: float, lam: float):
    """``Q = 1 / (C (1 + lambda) + lambda DEPTH_DAMPING)`` of one depth variable; 0 where ``C == 0`` (unobserved)."""
    if c > 0.0:
        return 1.0 / (c * (1.0 + lam) + lam * DEPTH_DAMPING)
    return 0.0


@wp.kernel
def window_copy_kernel(
    keyframes: wp.array(dtype=wp.int32),  # [n] buffer index of each window slot
    to_window: int,  # 1: buffer -> window; 0: window -> buffer
    disp_all: wp.array(dtype=float, ndim=4),  # [K,C,h,w] the buffer's inverse depths, 1/m
    poses_all: wp.array(dtype=wp.transform),  # [K] the buffer's T_w_b
    disp: wp.array(dtype=float, ndim=4),  # [n,C,h,w] the window's
    poses: wp.array(dtype=wp.transform),  # [n] the window's
):
    """Copy the window's inverse depths and rig poses out of the keyframe buffer, or back."""
    s, c, y, x = wp.tid()
    k = keyframes[s]
    first = c == 0 and y == 0 and x == 0
    if to_window != 0:
        disp[s, c, y, x] = disp_all[k, c, y, x]
        if first:
            poses[s] = poses_all[k]
    else:
        disp_all[k, c, y, x] = disp[s, c, y, x]
        if first:
            poses_all[k] = poses[s]


@wp.kernel
def prior_terms_kernel(
    C_corr: wp.array(dtype=float, ndim=4),  # [n,C,h,w] depth information from the correspondences
    w_corr: wp.array(dtype=float, ndim=4),  # [n,C,h,w] depth gradient from the correspondences
    disp: wp.array(dtype=float, ndim=4),  # [n,C,h,w] current inverse depth, 1/m
    target: wp.array(dtype=float, ndim=4),  # [n,C,h,w] prior inverse depth, 1/m
    mask: wp.array(dtype=float, ndim=4),  # [n,C,h,w] prior confidence (0: no prior)
    prior_weight: float,  # px^2 m^2
    C_out: wp.array(dtype=float, ndim=4),  # [n,C,h,w] out: C + pw mask
    w_out: wp.array(dtype=float, ndim=4),  # [n,C,h,w] out: w + pw mask (target - d)
):
    """Add the inverse-depth prior ``0.5 pw mask (target - d)^2`` to the depth block and gradient."""
    s, c, y, x = wp.tid()
    pm = prior_weight * mask[s, c, y, x]
    C_out[s, c, y, x] = C_corr[s, c, y, x] + pm
    w_out[s, c, y, x] = w_corr[s, c, y, x] + pm * (target[s, c, y, x] - disp[s, c, y, x])


@wp.kernel
def prior_cost_kernel(
    disp: wp.array(dtype=float, ndim=4),  # [n,C,h,w] inverse depth, 1/m
    target: wp.array(dtype=float, ndim=4),  # [n,C,h,w]
    mask: wp.array(dtype=float, ndim=4),  # [n,C,h,w]
    prior_weight: float,
    total: wp.array(dtype=wp.float64),  # [1] out (accumulated)
):
    """Prior cost ``0.5 pw sum mask (target - d)^2``, summed in float64."""
    s, c, y, x = wp.tid()
    m = mask[s, c, y, x]
    if m != 0.0:
        r = target[s, c, y, x] - disp[s, c, y, x]
        wp.atomic_add(total, 0, wp.float64(0.5 * prior_weight * m * r * r))


@wp.kernel
def sum_float64_kernel(values: wp.array(dtype=float), total: wp.array(dtype=wp.float64)):
    """``total[0] += sum(values)`` in float64 (per-edge costs into one number)."""
    i = wp.tid()
    wp.atomic_add(total, 0, wp.float64(values[i]))


@wp.kernel
def schur_pairs_kernel(
    Epix: wp.array(dtype=vec6, ndim=3),  # [E,h,w] pose-depth couplings E_j per pixel
    C: wp.array(dtype=float, ndim=4),  # [n,C,h,w] depth block (with prior), slot-indexed
    edges: wp.array(dtype=wp.vec4i),  # [E] (slot i, ci, slot j, cj)
    pairs: wp.array(dtype=wp.vec2i),  # [P] (e1, e2): pose edges leaving the same view (i, ci)
    lam: float,  # Levenberg-Marquardt damping of the depth block
    p0: int,  # first pair of this launch (a band of pairs: see mcgs_warp.kernels.launch)
    blocks: wp.array(dtype=mat66d, ndim=2),  # [P,4] out (accumulated, float64): block 3 = (j1,j2)
):
    """Per pair and image row: ``M = sum_p Q_p E_{e1,j}(p) E_{e2,j}(p)^T`` into block 3;
    :func:`schur_pair_blocks_kernel` derives the other three."""
    p, y = wp.tid()
    p = p + p0
    e1 = pairs[p][0]
    e2 = pairs[p][1]
    edge = edges[e1]
    s = edge[0]
    c = edge[1]
    M = mat66()
    for x in range(Epix.shape[2]):
        q = schur_depth_weight(C[s, c, y, x], lam)
        if q > 0.0:
            M = M + wp.outer(q * Epix[e1, y, x], Epix[e2, y, x])
    wp.atomic_add(blocks, p, 3, mat66d(M))


@wp.kernel
def schur_pair_blocks_kernel(
    pairs: wp.array(dtype=wp.vec2i),  # [P] (e1, e2)
    Ad: wp.array(dtype=mat66),  # [E] edge_adjoint per edge
    blocks: wp.array(dtype=mat66d, ndim=2),  # [P,4] in: block 3 = M; out: (i,i), (i,j2), (j1,i)
):
    """``(i,i) = Ad1^T M Ad2``, ``(i,j2) = -Ad1^T M``, ``(j1,i) = -M Ad2`` (float64)."""
    p = wp.tid()
    M = blocks[p, 3]
    A1t = wp.transpose(mat66d(Ad[pairs[p][0]]))
    A2 = mat66d(Ad[pairs[p][1]])
    A1tM = A1t * M
    blocks[p, 0] = A1tM * A2
    blocks[p, 1] = -A1tM
    blocks[p, 2] = -(M * A2)


@wp.kernel
def schur_rhs_kernel(
    Epix: wp.array(dtype=vec6, ndim=3),  # [E,h,w] E_j per pixel
    Ad: wp.array(dtype=mat66),  # [E] edge_adjoint per edge
    C: wp.array(dtype=float, ndim=4),  # [n,C,h,w] depth block (with prior)
    wdepth: wp.array(dtype=float, ndim=4),  # [n,C,h,w] depth gradient (with prior)
    edges: wp.array(dtype=wp.vec4i),  # [E] slot-indexed
    pose_edges: wp.array(dtype=wp.int32),  # [Ep] edges with i != j
    lam: float,
    k0: int,  # first pose edge of this launch
    out: wp.array(dtype=vec6d, ndim=2),  # [E,2] out (accumulated, float64): sum_p E_{e,i} Q w, sum_p E_{e,j} Q w
):
    """Per pose edge and image row, the depth part of the reduced gradient ``E C^-1 w``
    (pose i's part ``-Ad^T`` pose j's)."""
    k, y = wp.tid()
    k = k + k0
    e = pose_edges[k]
    s = edges[e][0]
    c = edges[e][1]
    acc = vec6()
    for x in range(Epix.shape[2]):
        qw = schur_depth_weight(C[s, c, y, x], lam) * wdepth[s, c, y, x]
        if qw != 0.0:
            acc = acc + qw * Epix[e, y, x]
    acc_d = vec6d(acc)
    wp.atomic_add(out, e, 0, -(wp.transpose(mat66d(Ad[e])) * acc_d))
    wp.atomic_add(out, e, 1, acc_d)


@wp.kernel
def schur_scatter_kernel(
    blocks: wp.array(dtype=mat66d, ndim=2),  # [P,4] schur_pairs_kernel's blocks
    pairs: wp.array(dtype=wp.vec2i),  # [P] (e1, e2), e1 <= e2
    edges: wp.array(dtype=wp.vec4i),  # [E] slot-indexed
    S: wp.array(dtype=wp.float64, ndim=2),  # [6n,6n] out (accumulated): minus the blocks
):
    """Subtract the pair blocks from the reduced camera system in float64; a pair with
    ``e1 != e2`` stands for (e2, e1) too, whose blocks are the transposes."""
    p, k, a, b = wp.tid()
    e1 = pairs[p][0]
    e2 = pairs[p][1]
    r = edges[e1][0]  # (i, .) blocks
    if k >= 2:
        r = edges[e1][2]  # (j1, .)
    c = edges[e1][0]  # (., i)
    if k == 1 or k == 3:
        c = edges[e2][2]  # (., j2)
    v = -blocks[p, k][a, b]
    wp.atomic_add(S, 6 * r + a, 6 * c + b, v)
    if e1 != e2:
        wp.atomic_add(S, 6 * c + b, 6 * r + a, v)


@wp.kernel
def pose_system_kernel(
    H: wp.array(dtype=mat66d, ndim=2),  # [E,3] H_ii, H_ij, H_jj
    g: wp.array(dtype=vec6d, ndim=2),  # [E,2] v_i, v_j
    depth_rhs: wp.array(dtype=vec6d, ndim=2),  # [E,2] schur_rhs_kernel's E C^-1 w
    edges: wp.array(dtype=wp.vec4i),  # [E] slot-indexed
    pose_edges: wp.array(dtype=wp.int32),  # [Ep]
    S: wp.array(dtype=wp.float64, ndim=2),  # [6n,6n] out (accumulated): + B
    rhs: wp.array(dtype=wp.float64),  # [6n] out (accumulated): + v - E C^-1 w
):
    """Add the pose blocks B of each pose edge (``H_ji = H_ij^T``) and the reduced gradient, in float64."""
    k, a, b = wp.tid()
    e = pose_edges[k]
    i = 6 * edges[e][0]
    j = 6 * edges[e][2]
    wp.atomic_add(S, i + a, i + b, H[e, 0][a, b])
    wp.atomic_add(S, i + a, j + b, H[e, 1][a, b])
    wp.atomic_add(S, j + b, i + a, H[e, 1][a, b])
    wp.atomic_add(S, j + a, j + b, H[e, 2][a, b])
    if b == 0:
        wp.atomic_add(rhs, i + a, g[e, 0][a] - depth_rhs[e, 0][a])
        wp.atomic_add(rhs, j + a, g[e, 1][a] - depth_rhs[e, 1][a])


@wp.kernel
def edge_step_kernel(
    Ad: wp.array(dtype=mat66),  # [E] edge_adjoint per edge
    edges: wp.array(dtype=wp.vec4i),  # [E] slot-indexed
    pose_edges: wp.array(dtype=wp.int32),  # [Ep]
    dxi: wp.array(dtype=vec6),  # [n] pose steps
    step: wp.array(dtype=vec6),  # [E] out: dxi_j - Ad dxi_i (E_i . dxi_i + E_j . dxi_j = E_j . step)
):
    k = wp.tid()
    e = pose_edges[k]
    step[e] = dxi[edges[e][2]] - Ad[e] * dxi[edges[e][0]]


@wp.kernel
def backsub_coupling_kernel(
    Epix: wp.array(dtype=vec6, ndim=3),  # [E,h,w] E_j per pixel
    edges: wp.array(dtype=wp.vec4i),  # [E] slot-indexed
    pose_edges: wp.array(dtype=wp.int32),  # [Ep]
    step: wp.array(dtype=vec6),  # [E] edge_step_kernel's dxi_j - Ad dxi_i
    acc: wp.array(dtype=float, ndim=4),  # [n,C,h,w] out (accumulated): sum_e E_e(p) . dxi
):
    """The pose part of the back-substitution, ``E^T dxi``, per depth variable."""
    k, y, x = wp.tid()
    e = pose_edges[k]
    edge = edges[e]
    t = wp.dot(Epix[e, y, x], step[e])
    if t != 0.0:
        wp.atomic_add(acc, edge[0], edge[1], y, x, t)


@wp.kernel
def depth_candidate_kernel(
    disp: wp.array(dtype=float, ndim=4),  # [n,C,h,w] current inverse depth, 1/m
    C: wp.array(dtype=float, ndim=4),  # [n,C,h,w] depth block (with prior)
    wdepth: wp.array(dtype=float, ndim=4),  # [n,C,h,w] depth gradient (with prior)
    coupling: wp.array(dtype=float, ndim=4),  # [n,C,h,w] E^T dxi (backsub_coupling_kernel)
    lam: float,
    min_disp: float,  # 1/m
    cand: wp.array(dtype=float, ndim=4),  # [n,C,h,w] out: max(d + dd, min_disp) where d > 0, else 0
    nonfinite: wp.array(dtype=wp.int32),  # [1] out (accumulated): count of non-finite dd
):
    """Back-substitute ``dd = Q (w - E^T dxi)`` (eq. 10) and form the candidate inverse depths."""
    s, c, y, x = wp.tid()
    dd = schur_depth_weight(C[s, c, y, x], lam) * (wdepth[s, c, y, x] - coupling[s, c, y, x])
    if not wp.isfinite(dd):
        wp.atomic_add(nonfinite, 0, 1)
    d = disp[s, c, y, x]
    if d > 0.0:
        cand[s, c, y, x] = wp.max(d + dd, min_disp)
    else:
        cand[s, c, y, x] = 0.0


@wp.kernel
def pose_candidate_kernel(
    poses: wp.array(dtype=wp.transform),  # [n] T_w_b
    dxi: wp.array(dtype=vec6),  # [n] body-frame steps (rho, phi)
    cand: wp.array(dtype=wp.transform),  # [n] out: T_w_b @ Exp(dxi)
):
    s = wp.tid()
    cand[s] = se3_retract(poses[s], dxi[s])


# ---- JDSA (paper eq. 5): the scaled prior and the scale grids' normal equations ------------
# A view's m x n scale grid spans its whole padded grid (h x w): node rows sit at
# y (m - 1) / (h - 1), columns likewise, and B(p, s) interpolates bilinearly (the host
# reference is mcgs_warp.ba.jdsa.bilinear_basis, which these kernels reproduce).


@wp.func
def grid_cell(p: int, size: int, nodes: int):
    """Node index below pixel row (or column) ``p`` of ``size`` and the weight of the next
    node, for ``nodes`` grid nodes spread from the first pixel to the last."""
    if nodes < 2 or size < 2:
        return int(0), wp.float64(0.0)
    t = wp.float64(p) * (wp.float64(nodes - 1) / wp.float64(size - 1))
    i = wp.min(int(wp.floor(t)), nodes - 2)
    return i, t - wp.float64(i)


@wp.func
def grid_nodes(y: int, x: int, h: int, w: int, m: int, n: int):
    """The 4 nodes of an m x n grid around grid pixel (x, y) of h x w, as flat indices
    ``i n + j``, and their bilinear weights (summing to 1)."""
    i, fy = grid_cell(y, h, m)
    j, fx = grid_cell(x, w, n)
    i1 = wp.min(i + 1, m - 1)
    j1 = wp.min(j + 1, n - 1)
    one = wp.float64(1.0)
    nodes = wp.vec4i(i * n + j, i * n + j1, i1 * n + j, i1 * n + j1)
    return nodes, wp.vec4d((one - fy) * (one - fx), (one - fy) * fx, fy * (one - fx), fy * fx)


@wp.func
def scale_at(scales: wp.array(dtype=wp.float64, ndim=4), k: int, c: int, y: int, x: int, h: int, w: int):
    """The bilinear scale ``B(p, s)`` of view (k, c) at grid pixel (x, y)."""
    n = scales.shape[3]
    nodes, weights = grid_nodes(y, x, h, w, scales.shape[2], n)
    s = wp.float64(0.0)
    for r in range(4):
        s += weights[r] * scales[k, c, nodes[r] // n, nodes[r] % n]
    return s


@wp.kernel
def scaled_prior_kernel(
    depth_prior: wp.array(dtype=float, ndim=4),  # [K,C,h,w] m, 0 = none
    prior_conf: wp.array(dtype=float, ndim=4),  # [K,C,h,w] in [0,1]
    scales: wp.array(dtype=wp.float64, ndim=4),  # [K,C,m,n] JDSA scale grids
    kf: wp.array(dtype=wp.int32),  # [S] buffer keyframe of each window slot
    target: wp.array(dtype=float, ndim=4),  # [S,C,h,w] out: inverse depth of the scaled prior, 1/m (0 = none)
    mask: wp.array(dtype=float, ndim=4),  # [S,C,h,w] out: its confidence (0 = none)
):
    """MCBA's prior for a window: ``1 / (d+(p) B(p, s))`` and the prior's confidence."""
    s, c, y, x = wp.tid()
    k = kf[s]
    scaled = wp.float64(depth_prior[k, c, y, x]) * scale_at(scales, k, c, y, x, depth_prior.shape[2], depth_prior.shape[3])
    if scaled > wp.float64(0.0):
        target[s, c, y, x] = float(wp.float64(1.0) / scaled)
        mask[s, c, y, x] = prior_conf[k, c, y, x]
    else:
        target[s, c, y, x] = 0.0
        mask[s, c, y, x] = 0.0


@wp.kernel
def jdsa_normal_kernel(
    depth_prior: wp.array(dtype=float, ndim=4),  # [K,C,h,w] m, 0 = none
    prior_conf: wp.array(dtype=float, ndim=4),  # [K,C,h,w]
    disp: wp.array(dtype=float, ndim=4),  # [K,C,h,w] current inverse depth, 1/m
    info: wp.array(dtype=float, ndim=4),  # [S,C,h,w] MCBA depth information per window slot
    kf: wp.array(dtype=wp.int32),  # [V] buffer keyframe of each fitted keyframe
    info_slot: wp.array(dtype=wp.int32),  # [V] its slot in ``info``; -1: unweighted (no information given)
    m: int,
    n: int,
    AtA: wp.array(dtype=wp.float64, ndim=4),  # [V,C,m*n,m*n] out (accumulated)
    Atb: wp.array(dtype=wp.float64, ndim=3),  # [V,C,m*n] out (accumulated)
    weight_sum: wp.array(dtype=wp.float64, ndim=2),  # [V,C] out (accumulated): total pixel weight
):
    """Normal equations of ``min_s sum_p wt (d+(p) B(p, s) - D(p))^2`` per view (the scale
    fit of :func:`mcgs_warp.ba.jdsa.solve_scales`), ``D = 1 / disp``; the pixel weight
    ``wt`` is the prior's confidence times, with information, ``info disp^4`` (the
    inverse variance of D from the correspondences). Each pixel touches 4 grid nodes.
    Atomic sums: launch it once (not in CPU bands; Warp's CPU atomics are plain adds)."""
    v, c, y, x = wp.tid()
    k = kf[v]
    h = depth_prior.shape[2]
    w = depth_prior.shape[3]
    prior = wp.float64(depth_prior[k, c, y, x])
    d = wp.float64(disp[k, c, y, x])
    if prior <= wp.float64(0.0) or d <= wp.float64(0.0):
        return
    wt = wp.float64(prior_conf[k, c, y, x])
    slot = info_slot[v]
    if slot >= 0:
        wt = wt * wp.float64(info[slot, c, y, x]) * d * d * d * d
    if wt <= wp.float64(0.0):
        return
    depth = wp.float64(1.0) / d
    nodes, weights = grid_nodes(y, x, h, w, m, n)
    a = weights * prior  # d(d+ B(p, s)) / d s at the 4 nodes
    for r in range(4):
        wp.atomic_add(Atb, v, c, nodes[r], wt * a[r] * depth)
        for q in range(4):
            wp.atomic_add(AtA, v, c, nodes[r], nodes[q], wt * a[r] * a[q])
    wp.atomic_add(weight_sum, v, c, wt)
