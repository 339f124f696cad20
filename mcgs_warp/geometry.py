"""NumPy rigid-body helpers for host code (readers, rigs, evaluation).

Poses are 4x4 float64 matrices ``T_a_b`` (frame b -> frame a); quaternions are
``(x, y, z, w)`` as in Warp (DESIGN.md). The Warp-side twins live in
``mcgs_warp.kernels.se3``.
"""

from __future__ import annotations

import numpy as np


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of quaternions [..., 4] ``(x, y, z, w)`` (normalized here)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(R) -> np.ndarray:
    """Unit quaternions [..., 4] ``(x, y, z, w)`` with ``w >= 0`` of rotation matrices [..., 3, 3]."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((len(flat), 4))
    for k, m in enumerate(flat):
        tr = np.trace(m)
        if tr > 0:
            s = 2.0 * np.sqrt(1.0 + tr)
            q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
        q = np.asarray(q)
        out[k] = q * (1.0 if q[3] >= 0 else -1.0) / np.linalg.norm(q)
    return out.reshape(R.shape[:-2] + (4,))


def pose(translation, quat_xyzw) -> np.ndarray:
    """4x4 pose from a translation [3] and a quaternion [4] ``(x, y, z, w)``; batched over [..., ]."""
    t = np.asarray(translation, dtype=np.float64)
    T = np.zeros(t.shape[:-1] + (4, 4))
    T[..., :3, :3] = quat_to_matrix(quat_xyzw)
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert(T) -> np.ndarray:
    """Inverse of rigid transforms [..., 4, 4] (using the rotation's transpose)."""
    T = np.asarray(T, dtype=np.float64)
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = R
    out[..., :3, 3] = -(R @ T[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) of rotation matrices [...,3,3], accurate near 0 and pi."""
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.arctan2(0.5 * np.linalg.norm(w, axis=-1), 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0))


def pose_distance(A, B) -> tuple[float, float]:
    """How far apart two rigid transforms are: translation (m) and angle (rad) of ``A^-1 B``."""
    D = invert(A) @ np.asarray(B, dtype=np.float64)
    return float(np.linalg.norm(D[:3, 3])), float(rotation_angle(D[:3, :3]))


def rotation_error(R, tol: float = 1e-4) -> str | None:
    """Why ``R`` [3,3] is not a rotation (orthonormal, det +1) within ``tol``, or None."""
    R = np.asarray(R, dtype=np.float64)
    if not np.all(np.isfinite(R)):
        return "contains NaN or Inf"
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > tol:
        return f"rotation part is not orthonormal (max |R^T R - I| = {err:.2e})"
    if np.linalg.det(R) < 0:
        return "rotation part is a reflection (det = -1)"
    return None


def yaw_pitch_roll(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (radians)."""
    cz, sz, cy, sy, cx, sx = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    return Rz @ Ry @ Rx


def matrix_to_transform7(T) -> np.ndarray:
    """4x4 poses [..., 4, 4] -> Warp ``wp.transform`` layout [..., 7]: (px py pz qx qy qz qw)."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :3, 3], matrix_to_quat(T[..., :3, :3])], axis=-1)


def transform7_to_matrix(t) -> np.ndarray:
    """Warp ``wp.transform`` layout [..., 7] -> 4x4 poses [..., 4, 4]."""
    t = np.asarray(t, dtype=np.float64)
    return pose(t[..., :3], t[..., 3:])


def se3_exp(xi) -> np.ndarray:
    """``Exp(xi)`` as a 4x4 matrix for ``xi = (rho, phi)`` [..., 6] (DESIGN.md convention)."""
    xi = np.asarray(xi, dtype=np.float64)
    rho, phi = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = np.zeros(xi.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -phi[..., 2], phi[..., 1], -phi[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    small = theta < 1e-8
    t2 = np.where(small, 1.0, theta * theta)
    A = np.where(small, 1.0, np.sin(theta) / np.where(small, 1.0, theta))
    B = np.where(small, 0.5, (1 - np.cos(theta)) / t2)
    Cc = np.where(small, 1.0 / 6.0, (theta - np.sin(theta)) / (t2 * np.where(small, 1.0, theta)))
    I = np.eye(3)
    R = I + A * K + B * (K @ K)
    V = I + B * K + Cc * (K @ K)
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = (V @ rho[..., None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def hat(v: np.ndarray) -> np.ndarray:
    """The skew matrix [3,3] of ``v`` [3]: ``hat(v) @ x == cross(v, x)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector [3] of ``R`` [3,3]."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-8:
        return 0.5 * w
    if np.pi - th < 1e-6:  # near pi: from the symmetric part
        A = (R + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(A)))
        axis = A[:, i] / np.sqrt(max(A[i, i], 1e-300))
        return th * axis / np.linalg.norm(axis)
    return th / (2.0 * np.sin(th)) * w


def so3_left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """Inverse [3,3] of SO(3)'s left Jacobian at rotation vector ``phi``: ``rho = J^-1 t`` in :func:`se3_log`."""
    th = np.linalg.norm(phi)
    K = hat(phi)
    if th < 1e-6:
        return np.eye(3) - 0.5 * K + K @ K / 12.0
    return np.eye(3) - 0.5 * K + (1.0 / th**2 - (1 + np.cos(th)) / (2 * th * np.sin(th))) * K @ K


def se3_log(T: np.ndarray) -> np.ndarray:
    """``(rho, phi)`` [6] with ``se3_exp(xi) == T`` (the inverse of :func:`~mcgs_warp.geometry.se3_exp`)."""
    phi = so3_log(T[:3, :3])
    return np.concatenate([so3_left_jacobian_inv(phi) @ T[:3, 3], phi])


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of a 4x4 pose for ``(rho, phi)`` ordering: ``T Exp(x) T^-1 = Exp(Ad x)``."""
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[:3, 3:] = tx @ R
    A[3:, 3:] = R
    return A
