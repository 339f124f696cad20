"""SE(3) and SO(3) helpers as Warp functions.

Conventions (DESIGN.md, "Frames, poses, units"): a pose ``T_a_b`` is a
``wp.transform`` (translation, quaternion ``(x, y, z, w)``) mapping points from
frame b to frame a. Tangent vectors are ``xi = (rho, phi)`` (translation first) in
a ``vec6``; increments are right-multiplied, ``T <- T @ Exp(xi)``, so ``xi`` lives in
the frame on the right (the body frame for ``T_w_b``). The adjoint satisfies
``T @ Exp(xi) @ inv(T) = Exp(Ad(T) @ xi)``.
"""

from __future__ import annotations

import warp as wp

vec6 = wp.types.vector(6, dtype=wp.float32)
mat66 = wp.types.matrix(shape=(6, 6), dtype=wp.float32)


@wp.func
def skew(v: wp.vec3):
    """Cross-product matrix: ``skew(a) @ b = cross(a, b)``."""
    return wp.mat33(0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0)


@wp.func
def so3_exp(phi: wp.vec3):
    """Unit quaternion of the rotation vector ``phi`` (radians)."""
    angle = wp.length(phi)
    if angle < 1.0e-8:
        q = wp.quat(0.5 * phi[0], 0.5 * phi[1], 0.5 * phi[2], 1.0)
        return wp.normalize(q)
    return wp.quat_from_axis_angle(phi / angle, angle)


@wp.func
def so3_log(q: wp.quat):
    """Rotation vector of unit quaternion ``q``, angle in [0, pi]."""
    w = q[3]
    v = wp.vec3(q[0], q[1], q[2])
    if w < 0.0:
        w = -w
        v = -v
    s = wp.length(v)
    if s < 1.0e-8:
        return (2.0 / w) * v
    return (2.0 * wp.atan2(s, w) / s) * v


@wp.func
def so3_left_jacobian(phi: wp.vec3):
    """Left Jacobian ``V`` of SO(3): ``Exp((rho, phi))`` has translation ``V @ rho``."""
    theta2 = wp.dot(phi, phi)
    K = skew(phi)
    I = wp.identity(n=3, dtype=float)
    if theta2 < 1.0e-10:
        return I + 0.5 * K + (1.0 / 6.0) * (K * K)
    theta = wp.sqrt(theta2)
    a = (1.0 - wp.cos(theta)) / theta2
    b = (theta - wp.sin(theta)) / (theta2 * theta)
    return I + a * K + b * (K * K)


@wp.func
def se3_exp(xi: vec6):
    """``Exp(xi)`` for ``xi = (rho, phi)``."""
    rho = wp.vec3(xi[0], xi[1], xi[2])
    phi = wp.vec3(xi[3], xi[4], xi[5])
    return wp.transform(so3_left_jacobian(phi) * rho, so3_exp(phi))


@wp.func
def se3_log(T: wp.transform):
    """``Log(T)`` as ``(rho, phi)``; inverse of :func:`se3_exp` for angles below pi."""
    phi = so3_log(wp.transform_get_rotation(T))
    rho = wp.inverse(so3_left_jacobian(phi)) * wp.transform_get_translation(T)
    return vec6(rho[0], rho[1], rho[2], phi[0], phi[1], phi[2])


@wp.func
def se3_compose(T_a_b: wp.transform, T_b_c: wp.transform):
    """``T_a_c = T_a_b @ T_b_c``."""
    return wp.transform_multiply(T_a_b, T_b_c)


@wp.func
def se3_inverse(T_a_b: wp.transform):
    """``T_b_a = inv(T_a_b)``."""
    return wp.transform_inverse(T_a_b)


@wp.func
def se3_retract(T: wp.transform, xi: vec6):
    """Right-multiplied increment ``T @ Exp(xi)``."""
    return wp.transform_multiply(T, se3_exp(xi))


@wp.func
def se3_adjoint(T: wp.transform):
    """6x6 adjoint of ``T`` for ``(rho, phi)`` ordering: ``[[R, skew(t) R], [0, R]]``."""
    R = wp.quat_to_matrix(wp.transform_get_rotation(T))
    tR = skew(wp.transform_get_translation(T)) * R
    A = mat66()
    for i in range(3):
        for j in range(3):
            A[i, j] = R[i, j]
            A[i, j + 3] = tR[i, j]
            A[i + 3, j + 3] = R[i, j]
    return A
