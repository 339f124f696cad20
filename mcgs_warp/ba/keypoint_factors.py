"""Keypoint reprojection factors inside MCBA (issue: keypoints keep the poses where the
dense grid matches are few).

A keypoint track is one 3D point seen by several keyframe views: it has a source view
(slot ``i``, camera ``ci``, unit-depth ray ``r``) and its own inverse depth ``d``, exactly
like a grid pixel, and observations in other views (slot ``j``, camera ``cj``, observed
pixel ``p``) with a weight. The residual is the dense one, ``Pi_cj(T_cj_ci r / d) - p`` in
reduced-grid pixels (full-resolution pixels / stride), with the same robust Huber cost, so
the two kinds of factor add up in one Gauss-Newton system. Each track's depth couples only
to the poses its observations touch: the depth block stays diagonal and is eliminated by
the same Schur complement (eq. 10) before the reduced camera system is solved; the terms
here are added to it. A track whose source depth is exact sensor depth keeps it (no unknown):
left free, the window's depths and poses trade scale for a better fit of pixel noise (the
keypoint odometry's steps came out 1.5-3.4 % short with exact depth on clean images).
NumPy, float64: a window holds a few thousand observations.

Pose increments are right-multiplied in the body frame, ``(rho, phi)`` (DESIGN.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import camera64

DEPTH_DAMPING = 1.0e4  # as kernels/ba.py: Q = 1 / (C (1 + lambda) + lambda DEPTH_DAMPING)


def _skew(v: np.ndarray) -> np.ndarray:
    """[N,3] -> [N,3,3] cross-product matrices."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def project_by_camera(cams, cam_of: np.ndarray, X: np.ndarray, jac: bool = False):
    """Pixels [n,2] of camera-frame points ``X`` [n,3], each in its camera ``cams[cam_of[i]]``
    (Warp camera structs; the float64 host model, :mod:`.camera64`), their analytic Jacobians
    [n,2,3] (with ``jac``),
    validity [n] (in the model's domain, finite) and the points used ([n,3]; invalid ones
    replaced by +z so that nothing downstream divides by zero)."""
    n = len(X)
    uv, J = np.zeros((n, 2)), (np.zeros((n, 2, 3)) if jac else None)
    valid, used = np.zeros(n, bool), np.tile([0.0, 0.0, 1.0], (n, 1))
    for c, cam in enumerate(cams):
        m = cam_of == c
        if not m.any():
            continue
        uv[m], valid[m], Jm = camera64.project(cam, X[m], jacobian=jac)
        used[m] = np.where(valid[m][:, None], X[m], [0.0, 0.0, 1.0])
        if jac:
            J[m] = Jm
    return uv, J, valid, used


@dataclass
class KeypointProblem:
    """The keypoint tracks of one MCBA window (slots index the window's keyframes)."""

    src_slot: np.ndarray  # [T] int
    src_cam: np.ndarray  # [T] int
    rays: np.ndarray  # [T,3] unit-depth rays of the source keypoints (source camera frame)
    disp: np.ndarray  # [T] float64 inverse depth along them, 1/m
    obs_track: np.ndarray  # [O] int
    obs_slot: np.ndarray  # [O] int
    obs_cam: np.ndarray  # [O] int
    obs_uv: np.ndarray  # [O,2] observed full-resolution pixels
    obs_weight: np.ndarray  # [O] confidence of each observation
    held: np.ndarray | None = None  # [T] bool: the source's depth is exact sensor depth, held (not solved)

    def __len__(self) -> int:
        return len(self.obs_track)


class KeypointFactors:
    """Linearization, Schur terms, candidate and cost of a :class:`KeypointProblem` for
    :meth:`mcgs_warp.ba.mcba.MCBA.solve` (same Huber threshold, same grid-pixel units)."""

    def __init__(self, problem: KeypointProblem, rig, stride: int, huber_delta: float, min_disp: float):
        self.p, self.stride, self.delta, self.min_disp = problem, stride, huber_delta, min_disp
        self.cams = [c.warp_camera() for c in rig.cameras]
        self.T_b_c = np.stack([c.T_b_c for c in rig.cameras])
        self.disp = problem.disp.astype(np.float64).copy()
        self.disp_c = self.disp.copy()

    # geometry --------------------------------------------------------------------------
    def _points(self, poses: np.ndarray, disp: np.ndarray):
        """Per observation: X_bi, X_w, X_bj, X_cj [O,3] at window poses [n,4,4]."""
        p = self.p
        t = p.obs_track
        X_ci = p.rays[t] / disp[t, None]
        Tbc_i = self.T_b_c[p.src_cam[t]]
        X_bi = np.einsum("oij,oj->oi", Tbc_i[:, :3, :3], X_ci) + Tbc_i[:, :3, 3]
        Twb_i = poses[p.src_slot[t]]
        X_w = np.einsum("oij,oj->oi", Twb_i[:, :3, :3], X_bi) + Twb_i[:, :3, 3]
        Twb_j = poses[p.obs_slot]
        X_bj = np.einsum("oji,oj->oi", Twb_j[:, :3, :3], X_w - Twb_j[:, :3, 3])
        Tbc_j = self.T_b_c[p.obs_cam]
        X_cj = np.einsum("oji,oj->oi", Tbc_j[:, :3, :3], X_bj - Tbc_j[:, :3, 3])
        return X_ci, X_bi, X_w, X_bj, X_cj

    def _project(self, X_cj: np.ndarray, jac: bool = False):
        """Predicted full-resolution pixels [O,2] (and their Jacobians [O,2,3]), valid [O]."""
        uv, J, valid, _ = project_by_camera(self.cams, self.p.obs_cam, X_cj, jac)
        return uv, J, valid

    def residuals(self, poses: np.ndarray, disp: np.ndarray):
        """Residuals [O,2] (predicted - observed, grid px) and validity [O]."""
        X_cj = self._points(poses, disp)[-1]
        uv, _, valid = self._project(X_cj)
        return (uv - self.p.obs_uv) / self.stride, valid & (disp[self.p.obs_track] > 0)

    def cost(self, poses: np.ndarray, disp: np.ndarray | None = None) -> float:
        e, valid = self.residuals(poses, self.disp if disp is None else disp)
        s = np.sqrt(self.p.obs_weight) * np.linalg.norm(e, axis=1)
        c = np.where(s <= self.delta, 0.5 * s * s, self.delta * (s - 0.5 * self.delta))
        return float(np.sum(np.where(valid, c, 0.0)))

    def jacobians(self, poses: np.ndarray):
        """Residuals e [O,2], Jacobians of the prediction w.r.t. pose i [O,2,6], pose j
        [O,2,6] and inverse depth [O,2] (grid px), validity [O]."""
        p = self.p
        t = p.obs_track
        X_ci, X_bi, X_w, X_bj, X_cj = self._points(poses, self.disp)
        uv, Jp, valid = self._project(X_cj, jac=True)
        Jp = Jp / self.stride
        R_cj_b = np.transpose(self.T_b_c[p.obs_cam][:, :3, :3], (0, 2, 1))
        R_bj_w = np.transpose(poses[p.obs_slot][:, :3, :3], (0, 2, 1))
        R_w_bi = poses[p.src_slot[t]][:, :3, :3]
        R_bi_ci = self.T_b_c[p.src_cam[t]][:, :3, :3]
        A_j = Jp @ R_cj_b  # d uv / d X_bj
        A_w = A_j @ R_bj_w  # d uv / d X_w
        dXbi_dxi = np.concatenate([np.broadcast_to(np.eye(3), (len(t), 3, 3)), -_skew(X_bi)], axis=2)  # d (Exp(xi) X_bi) / d (rho, phi)
        J_i = A_w @ R_w_bi @ dXbi_dxi
        J_j = A_j @ np.concatenate([-np.broadcast_to(np.eye(3), (len(t), 3, 3)), _skew(X_bj)], axis=2)
        dX_ci_dd = -X_ci / self.disp[t, None]
        J_d = np.einsum("oij,oj->oi", A_w @ R_w_bi @ R_bi_ci, dX_ci_dd)
        e = (uv - p.obs_uv) / self.stride
        return e, J_i, J_j, J_d, valid & (self.disp[t] > 0)

    def noise(self, poses: np.ndarray):
        """The tracks' measured noise (:func:`~mcgs_warp.ba.variance.robust_variance` of the
        whitened residual components; each track's point is an unknown they determine)."""
        from .variance import robust_variance

        e, valid = self.residuals(poses, self.disp)
        z = (np.sqrt(self.p.obs_weight)[:, None] * e)[valid]
        return robust_variance(z, unknowns=len(np.unique(self.p.obs_track[valid])))

    # Gauss-Newton terms -----------------------------------------------------------------
    def reduced_terms(self, poses: np.ndarray, lam: float):
        """The keypoint part of the reduced camera system: ``S`` [6n,6n] and ``rhs`` [6n]
        (to add to MCBA's, same sign convention: the step solves ``S dxi = rhs``)."""
        p, n = self.p, len(poses)
        e, J_i, J_j, J_d, valid = self.jacobians(poses)
        s = np.sqrt(p.obs_weight) * np.linalg.norm(e, axis=1)
        W = np.where(valid, p.obs_weight * np.where(s <= self.delta, 1.0, self.delta / np.maximum(s, 1e-300)), 0.0)
        A = np.concatenate([J_i, J_j], axis=2)  # [O,2,12]
        idx = np.concatenate([6 * p.src_slot[p.obs_track][:, None] + np.arange(6), 6 * p.obs_slot[:, None] + np.arange(6)], axis=1)  # [O,12]
        S = np.zeros((6 * n, 6 * n))
        g = np.zeros(6 * n)
        np.add.at(S, (idx[:, :, None], idx[:, None, :]), W[:, None, None] * np.einsum("oki,okj->oij", A, A))
        np.add.at(g, idx, W[:, None] * np.einsum("oki,ok->oi", A, e))
        T = len(p.disp)
        C = np.zeros(T)
        b = np.zeros(T)
        E = np.zeros((T, 6 * n))
        np.add.at(C, p.obs_track, W * np.einsum("ok,ok->o", J_d, J_d))
        np.add.at(b, p.obs_track, W * np.einsum("ok,ok->o", J_d, e))
        np.add.at(E, (p.obs_track[:, None], idx), W[:, None] * np.einsum("oki,ok->oi", A, J_d))
        den = C * (1.0 + lam) + lam * DEPTH_DAMPING
        Q = np.divide(1.0, den, out=np.zeros(T), where=C > 0)
        if p.held is not None:
            Q[p.held] = 0.0  # a held depth is no unknown: its terms stay on the poses, it takes no step
        self._C, self._b, self._E, self._Q = C, b, E, Q
        return S - E.T @ (Q[:, None] * E), -g + E.T @ (Q * b)

    def candidate(self, dxi: np.ndarray) -> None:
        """Back-substituted inverse depths ``max(d + Q (-b - E dxi), min_disp)`` of the last
        :meth:`reduced_terms` into ``disp_c``."""
        dd = self._Q * (-self._b - self._E @ dxi)
        self.disp_c = np.where(self.disp > 0, np.maximum(self.disp + dd, self.min_disp), 0.0)

    def accept(self) -> None:
        self.disp = self.disp_c.copy()


def window_poses(poses7) -> np.ndarray:
    """[n,4,4] float64 rig poses of a window's ``wp.transform`` array (host copy)."""
    from ..geometry import transform7_to_matrix

    return transform7_to_matrix(np.asarray(poses7, np.float64))

