"""Relative-pose factors in MCBA: a measured motion between two keyframes of the window.

The keypoint odometry (:mod:`mcgs_warp.frontend.keypoint_odometry`) tracks every frame and
measures the rig's motion ``M`` from keyframe ``a`` to keyframe ``b`` with a covariance; the
dense correspondences measure the same poses where they are many. Each pair adds

    r = Log(M^-1 T_a^-1 T_b)            (6-vector, (rho, phi) as DESIGN.md)

with information ``Lambda`` [6,6] (the odometry's inverse covariance, its keypoints' measured
variance included, times a weight) and a robust cost of the Mahalanobis length
``m = sqrt(r^T Lambda r)``: ``m^2 / 2`` up to ``huber`` (3: a 6-dof motion within its 3-sigma
ellipsoid), linear beyond, so a motion the odometry got wrong (a bad PnP) cannot drag the window.
Pose increments are right-multiplied in the body frame: with ``E = M^-1 T_a^-1 T_b``,
``d r / d xi_b = Jr^-1(r)`` and ``d r / d xi_a = -Jr^-1(r) Ad((T_a^-1 T_b)^-1)``. NumPy,
float64, added to MCBA's reduced camera system like :mod:`.keypoint_factors`.
"""

from __future__ import annotations

import numpy as np

from ..geometry import adjoint, hat, invert, se3_log, so3_left_jacobian_inv


def _q_matrix(rho: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """The off-diagonal block of the SE(3) left Jacobian (Barfoot's Q)."""
    th = np.linalg.norm(phi)
    P, Rh = hat(phi), hat(rho)
    if th < 1e-5:
        return 0.5 * Rh + (P @ Rh + Rh @ P + P @ Rh @ P) / 6.0
    s, c = np.sin(th), np.cos(th)
    return (0.5 * Rh + (th - s) / th**3 * (P @ Rh + Rh @ P + P @ Rh @ P)
            - (1 - th**2 / 2 - c) / th**4 * (P @ P @ Rh + Rh @ P @ P - 3 * P @ Rh @ P)
            - 0.5 * ((1 - th**2 / 2 - c) / th**4 - 3 * (th - s - th**3 / 6) / th**5) * (P @ Rh @ P @ P + P @ P @ Rh @ P))


def se3_right_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    """[6,6] inverse right Jacobian of SE(3) at ``xi = (rho, phi)``: ``Log(Exp(xi) Exp(d)) = xi + Jr^-1 d + O(d^2)``."""
    rho, phi = -xi[:3], -xi[3:]  # Jr(xi) = Jl(-xi)
    Jinv = so3_left_jacobian_inv(phi)
    out = np.zeros((6, 6))
    out[:3, :3] = out[3:, 3:] = Jinv
    out[:3, 3:] = -Jinv @ _q_matrix(rho, phi) @ Jinv
    return out


class RelativePoseFactors:
    """Pose factors between window slots (module docstring). ``pairs`` [P,2] slots ``(a, b)``,
    ``motions`` [P,4,4] measured ``T_a^-1 T_b``, ``information`` [P,6,6]."""

    def __init__(self, pairs, motions, information, huber: float = 3.0):
        self.huber = huber
        self.pairs = np.asarray(pairs, int).reshape(-1, 2)
        self.M_inv = np.stack([invert(M) for M in motions]) if len(motions) else np.zeros((0, 4, 4))
        self.info = np.asarray(information, np.float64).reshape(-1, 6, 6)

    def __len__(self) -> int:
        return len(self.pairs)

    def residuals(self, poses: np.ndarray) -> np.ndarray:
        """[P,6] ``Log(M^-1 T_a^-1 T_b)``."""
        return np.array([se3_log(Mi @ invert(poses[a]) @ poses[b]) for (a, b), Mi in zip(self.pairs, self.M_inv)], np.float64).reshape(-1, 6)

    def noise(self, _poses=None) -> float:
        """1: the information is in absolute units (the odometry's covariance carries its own
        measured variance), so MCBA weighs it by the dense class's variance alone (:mod:`.variance`)."""
        return 1.0

    def _mahalanobis(self, r: np.ndarray) -> np.ndarray:
        return np.sqrt(np.maximum(np.einsum("pi,pij,pj->p", r, self.info, r), 0.0))

    def cost(self, poses: np.ndarray, _disp=None) -> float:
        m = self._mahalanobis(self.residuals(poses))
        k = self.huber
        return float(np.sum(np.where(m <= k, 0.5 * m * m, k * (m - 0.5 * k))))

    def jacobians(self, poses: np.ndarray):
        """Residuals [P,6] and their Jacobians w.r.t. pose a and pose b [P,6,6]."""
        r = self.residuals(poses)
        Ja, Jb = np.zeros((len(r), 6, 6)), np.zeros((len(r), 6, 6))
        for p, (a, b) in enumerate(self.pairs):
            Jinv = se3_right_jacobian_inv(r[p])
            Jb[p] = Jinv
            Ja[p] = -Jinv @ adjoint(invert(invert(poses[a]) @ poses[b]))
        return r, Ja, Jb

    def reduced_terms(self, poses: np.ndarray, lam: float):
        """``S`` [6n,6n] and ``rhs`` [6n] (MCBA's sign convention: the step solves ``S dxi = rhs``)."""
        n = len(poses)
        S, rhs = np.zeros((6 * n, 6 * n)), np.zeros(6 * n)
        r, Ja, Jb = self.jacobians(poses)
        m = self._mahalanobis(r)
        W = np.where(m <= self.huber, 1.0, self.huber / np.maximum(m, 1e-300))  # Huber's IRLS weight
        for p, (a, b) in enumerate(self.pairs):
            J = np.concatenate([Ja[p], Jb[p]], axis=1)  # [6,12]
            idx = np.concatenate([np.arange(6 * a, 6 * a + 6), np.arange(6 * b, 6 * b + 6)])
            S[np.ix_(idx, idx)] += W[p] * J.T @ self.info[p] @ J
            rhs[idx] -= W[p] * J.T @ self.info[p] @ r[p]
        return S, rhs

    def candidate(self, dxi) -> None:  # no variables of its own
        pass

    def accept(self) -> None:
        pass
