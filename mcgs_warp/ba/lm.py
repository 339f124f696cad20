"""Levenberg-Marquardt: the one damping rule and damped pose step of every solver here.

MCBA (:mod:`.mcba`: dense correspondences, keypoint tracks, odometry and depth factors) and the
keypoint odometry's sliding-window bundle adjustment
(:class:`~mcgs_warp.frontend.keypoint_odometry.KeypointOdometry`) both eliminate their depths
or points (Schur complement) and solve the reduced pose system ``S dx = rhs`` (6 unknowns per
rig pose, right perturbation, some poses held) with Marquardt's diagonal damping. A step is
kept only where the robust cost does not rise; the damping then falls, else it grows and the
step is formed again, and the solve ends once the damping passes :data:`LAMBDA_MAX` (no step
lowers the cost: a minimum).
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg

LAMBDA_MIN, LAMBDA_MAX = 1e-9, 1e8


class Damping:
    """Marquardt's damping ``lam`` of one solve: /3 after an accepted step, x4 after a step
    that raised the cost, x10 after one that could not be formed (a singular system, a
    candidate state the solver refused); :attr:`exhausted` once it passes :data:`LAMBDA_MAX`."""

    def __init__(self, lam: float):
        self.lam = float(lam)

    def accepted(self) -> None:
        self.lam = max(self.lam / 3.0, LAMBDA_MIN)

    def rejected(self) -> None:
        self.lam *= 4.0

    def failed(self) -> None:
        self.lam *= 10.0

    @property
    def exhausted(self) -> bool:
        return self.lam > LAMBDA_MAX


def damped_step(S: np.ndarray, rhs: np.ndarray, free: np.ndarray, lam: float) -> np.ndarray:
    """The step [len(rhs)] solving ``(S + lam diag(S) + 1e-9 I) dx = rhs`` over the ``free``
    unknowns (indices; the others stay 0): NaN everywhere where that system cannot be solved
    (singular, or ill-conditioned: SciPy's ``LinAlgWarning`` is no step, the caller damps more)."""
    dx = np.zeros(len(rhs))
    if not len(free):
        return dx
    Sf = S[np.ix_(free, free)]
    Sf = Sf + lam * np.diag(np.diag(Sf)) + 1e-9 * np.eye(len(free))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", scipy.linalg.LinAlgWarning)
            dx[free] = scipy.linalg.solve(Sf, rhs[free], assume_a="sym")
    except (np.linalg.LinAlgError, ValueError, scipy.linalg.LinAlgWarning):
        dx[:] = np.nan
    return dx
