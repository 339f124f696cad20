"""Trajectory evaluation: timestamp association, Umeyama Sim(3) alignment, ATE and RPE.

ATE (absolute trajectory error) is the RMSE of positions after aligning the estimate
to the ground truth with the similarity (or, ``with_scale=False``, rigid) transform that
minimizes it (Umeyama 1991), as the TUM RGB-D benchmark tools and evo do. RPE is the
relative pose error as evo's ``evo_rpe`` defines it: for associated poses ``delta`` apart,
``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` (P estimate, Q ground truth), RMSE of its translation
norm (m) and of its rotation angle (degrees). It needs no alignment; with
``with_scale`` the estimate's translations are first multiplied by the Sim(3) scale (evo's
``--correct_scale``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..data.trajectory import Trajectory, nearest_timestamps
from ..errors import InputError
from ..geometry import invert, rotation_angle  # noqa: F401 (rotation_angle: also this module's API)


def associate(t_est: np.ndarray, t_gt: np.ndarray, max_dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (est, gt) of nearest timestamps within ``max_dt`` seconds (one-to-one)."""
    j = nearest_timestamps(t_est, t_gt, max_dt)
    i = np.nonzero(j >= 0)[0]
    j = j[i]
    _, first = np.unique(j, return_index=True)  # one estimate per ground-truth pose
    return i[first], j[first]


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True):
    """``(s, R, t)`` minimizing ``sum |dst - (s R src + t)|^2`` for points [N,3]."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var) if with_scale and var > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


@dataclass
class TrajectoryMetrics:
    ate_rmse_m: float
    ate_mean_m: float
    ate_max_m: float
    rpe_trans_m: float  # RMSE of the relative pose error's translation over pose pairs rpe_delta apart
    rpe_rot_deg: float  # RMSE of its rotation angle
    rpe_delta: int  # in associated poses (frames)
    scale: float
    path_length_m: float
    n_matched: int

    def to_dict(self) -> dict:
        return asdict(self)


def evaluate(est: Trajectory, gt: Trajectory, max_dt: float = 0.02, with_scale: bool = True, rpe_delta: int = 1, return_timestamps: bool = False):
    """ATE/RPE of ``est`` against ``gt``: returns ``(metrics, aligned estimate positions,
    matched ground-truth positions)``, and the matched estimate timestamps as a fourth
    item with ``return_timestamps=True``."""
    i, j = associate(est.timestamps, gt.timestamps, max_dt)
    if len(i) < 3:
        raise InputError(None, None, f"only {len(i)} estimated poses match ground-truth timestamps within {max_dt} s; need at least 3")
    P, G = est.positions[i], gt.positions[j]
    s, R, t = umeyama(P, G, with_scale)
    A = s * P @ R.T + t
    err = np.linalg.norm(A - G, axis=1)
    rpe_t, rpe_r = relative_pose_error(est.poses[i], gt.poses[j], rpe_delta, scale=s)
    metrics = TrajectoryMetrics(
        ate_rmse_m=float(np.sqrt(np.mean(err**2))),
        ate_mean_m=float(err.mean()),
        ate_max_m=float(err.max()),
        rpe_trans_m=rpe_t,
        rpe_rot_deg=rpe_r,
        rpe_delta=int(rpe_delta),
        scale=float(s),
        path_length_m=float(np.linalg.norm(np.diff(G, axis=0), axis=1).sum()),
        n_matched=int(len(i)),
    )
    return (metrics, A, G, est.timestamps[i]) if return_timestamps else (metrics, A, G)


def relative_pose_error(P: np.ndarray, Q: np.ndarray, delta: int = 1, scale: float = 1.0) -> tuple[float, float]:
    """evo-style RPE of associated estimate ``P`` and ground-truth ``Q`` poses [N,4,4] over
    the pairs ``(i, i + delta)``: ``(translation RMSE in m, rotation RMSE in degrees)``; the
    estimate's translations are multiplied by ``scale`` first. NaN with fewer than
    ``delta + 1`` poses."""
    if delta < 1:
        raise ValueError(f"delta: expected at least 1, got {delta}")
    if len(P) <= delta:
        return float("nan"), float("nan")
    P = np.array(P, np.float64)
    P[:, :3, 3] *= scale
    rel_est = invert(P[:-delta]) @ P[delta:]
    rel_gt = invert(Q[:-delta]) @ Q[delta:]
    E = invert(rel_gt) @ rel_est
    t = np.linalg.norm(E[:, :3, 3], axis=1)
    r = np.degrees(rotation_angle(E[:, :3, :3]))
    return float(np.sqrt(np.mean(t**2))), float(np.sqrt(np.mean(r**2)))
