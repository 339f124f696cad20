"""The camera models in float64 NumPy with analytic Jacobians, for the host-side solvers whose
Levenberg-Marquardt costs must be smooth to 1e-6 of a pose step (keypoint tracks, sensor-depth
alignment): float32 projection rounds pixels to ~5e-5 px and makes those costs step-shaped.

The same models as :mod:`mcgs_warp.kernels.camera` (pinhole with OpenCV radial-tangential
distortion, Kannala-Brandt fisheye, equirectangular; DESIGN.md), read from the Warp camera
struct; tests hold them against the kernels and against the independent float64 reference
(``kernels/reference.py``, whose Jacobians are central differences).
"""

from __future__ import annotations

import numpy as np

from ..kernels.camera import FAR, NEAR

PINHOLE, FISHEYE, EQUIRECTANGULAR = 0, 1, 2


def project(cam, X: np.ndarray, jacobian: bool = False, near: float = NEAR, far: float = FAR):
    """Pixels [M,2] of camera-frame points ``X`` [M,3] (m), whether each projects (finite,
    between ``near`` and ``far``, inside the model's domain: for pinhole and fisheye the squared
    normalized radius at most the camera's ``max_r2``) [M], and with ``jacobian`` ``d uv / d X``
    [M,2,3] (else None). Points that do not project get pixel 0 and Jacobian 0."""
    X = np.asarray(X, np.float64).reshape(-1, 3)
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    finite = np.isfinite(X).all(axis=1)
    with np.errstate(all="ignore"):
        if cam.model == EQUIRECTANGULAR:
            n2 = x * x + y * y + z * z
            ok = finite & (n2 >= near * near) & (n2 <= far * far) & (x * x + z * z > 1e-8 * n2)
        else:
            n2 = (x * x + y * y) / (z * z)
            ok = finite & (z >= near) & (z <= far) & (n2 <= np.float64(np.float32(cam.max_r2)))
    Xs = np.where(ok[:, None], X, [0.0, 0.0, 1.0])
    uv, J = _model(cam, Xs, jacobian)
    ok &= np.isfinite(uv).all(axis=1)
    uv = np.where(ok[:, None], uv, 0.0)
    if J is not None:
        J = np.where(ok[:, None, None], J, 0.0)
    return uv, ok, J


def _model(cam, X: np.ndarray, jacobian: bool):
    fx, fy = float(cam.fx), float(cam.fy)
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    M = len(X)
    if cam.model == EQUIRECTANGULAR:
        rho2 = x * x + z * z
        rho = np.sqrt(rho2)
        uv = np.stack([fx * np.arctan2(x, z) + cam.cx, fy * np.arctan2(y, rho) + cam.cy], axis=1)
        if not jacobian:
            return uv, None
        n2 = rho2 + y * y
        J = np.zeros((M, 2, 3))
        J[:, 0, 0], J[:, 0, 2] = fx * z / rho2, -fx * x / rho2
        J[:, 1, 0], J[:, 1, 1], J[:, 1, 2] = -fy * y * x / (rho * n2), fy * rho / n2, -fy * y * z / (rho * n2)
        return uv, J
    a, b = x / z, y / z
    d = np.array([cam.dist[k] for k in range(5)], np.float64)
    if cam.model == FISHEYE:
        r = np.hypot(a, b)
        th = np.arctan(r)
        t2 = th * th
        thd = th * (1 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))))
        small = r < 1e-12
        rs = np.where(small, 1.0, r)
        s = np.where(small, 1.0, thd / rs)
        ad, bd = s * a, s * b
        if jacobian:
            dthd = 1 + t2 * (3 * d[0] + t2 * (5 * d[1] + t2 * (7 * d[2] + t2 * 9 * d[3])))
            ds = np.where(small, 0.0, (dthd / (1 + r * r) * rs - thd) / (rs * rs))  # d s / d r
            ua, ub = np.where(small, 0.0, a / rs), np.where(small, 0.0, b / rs)  # d r / d (a, b)
            D = np.stack([np.stack([s + a * ds * ua, a * ds * ub], -1), np.stack([b * ds * ua, s + b * ds * ub], -1)], -2)
    else:
        k1, k2, p1, p2, k3 = d
        r2 = a * a + b * b
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        ad = a * radial + 2 * p1 * a * b + p2 * (r2 + 2 * a * a)
        bd = b * radial + p1 * (r2 + 2 * b * b) + 2 * p2 * a * b
        if jacobian:
            dr = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
            D = np.stack(
                [
                    np.stack([radial + 2 * a * a * dr + 2 * p1 * b + 6 * p2 * a, 2 * a * b * dr + 2 * p1 * a + 2 * p2 * b], -1),
                    np.stack([2 * a * b * dr + 2 * p1 * a + 2 * p2 * b, radial + 2 * b * b * dr + 6 * p1 * b + 2 * p2 * a], -1),
                ],
                -2,
            )
    uv = np.stack([fx * ad + cam.cx, fy * bd + cam.cy], axis=1)
    if not jacobian:
        return uv, None
    dn = np.zeros((M, 2, 3))  # d (a, b) / d X
    dn[:, 0, 0], dn[:, 0, 2] = 1 / z, -x / (z * z)
    dn[:, 1, 1], dn[:, 1, 2] = 1 / z, -y / (z * z)
    J = np.einsum("mij,mjk->mik", D, dn)
    J[:, 0] *= fx
    J[:, 1] *= fy
    return uv, J
