"""Levenberg-Marquardt: the one loop, damping rule and damped pose step of every solver here.

MCBA (:mod:`.mcba`: dense correspondences, keypoint tracks, odometry and depth factors), the
keypoint odometry's sliding-window bundle adjustment
(:class:`~mcgs_warp.frontend.keypoint_odometry.KeypointOdometry`), the two-view motion
(:mod:`~mcgs_warp.frontend.rig_motion`) and the rig PnP's refinement
(:class:`~mcgs_warp.frontend.pnp.RigPnP`) all run :func:`minimize`: linearize at the current
state, form a damped step and the candidate state it leads to, keep it only where the robust
cost does not rise (the damping then falls), else grow the damping and form the step again;
the solve ends after its iterations, once the damping passes its ceiling (no step lowers the
cost: a minimum), or where the caller calls the accepted step converged. The first three
eliminate their depths or points (Schur complement) and solve the reduced pose system
``S dx = rhs`` (6 unknowns per rig pose, right perturbation, some poses held) with Marquardt's
diagonal damping (:func:`damped_step`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import scipy.linalg

LAMBDA_MIN, LAMBDA_MAX = 1e-9, 1e8


class Damping:
    """Marquardt's damping ``lam`` of one solve and its schedule. By default (every solver but
    the PnP): /3 after an accepted step (never below :data:`LAMBDA_MIN`), x4 after a step that
    raised the cost, x10 after one that could not be formed (a singular system, a candidate
    state the solver refused); :attr:`exhausted` once it passes :data:`LAMBDA_MAX`.

    ``down`` is the accepted step's factor as a ratio ``(num, den)``, ``lam * num / den``, so
    that /3 is one exact division and the PnP's x0.3 one exact product; ``fail=math.inf`` makes
    a step that cannot be formed end the solve."""

    def __init__(self, lam: float, up: float = 4.0, down: tuple[float, float] = (1.0, 3.0), fail: float = 10.0, lo: float = LAMBDA_MIN, hi: float = LAMBDA_MAX):
        self.lam = float(lam)
        self.up, self.down, self.fail, self.lo, self.hi = up, down, fail, lo, hi

    def accepted(self) -> None:
        self.lam = max(self.lam * self.down[0] / self.down[1], self.lo)

    def rejected(self) -> None:
        self.lam *= self.up

    def failed(self) -> None:
        self.lam *= self.fail

    @property
    def exhausted(self) -> bool:
        return self.lam > self.hi


@dataclass
class LMResult:
    """How one :func:`minimize` ended: the cost of the state it left, and how many steps it
    kept and refused (refused: raised the cost, or could not be formed)."""

    cost: float
    accepted: int = 0
    rejected: int = 0


def minimize(
    cost: float,
    linearize: Callable[[float], Any],
    propose: Callable[[Any, float], float | None],
    accept: Callable[[float, float], bool | None],
    iterations: int,
    damping: Damping | None = None,
    strict: bool = False,
    retry: bool = True,
) -> LMResult:
    """Levenberg-Marquardt over a state the caller holds, from its robust ``cost``.

    Each of at most ``iterations`` iterations calls ``linearize(lam)`` once at the current state
    (``lam``: for a caller that damps inside its linearization, MCBA's depth block), then
    ``propose(lin, lam)``: form the damped step from that linearization and the candidate state
    it leads to, and return the candidate's cost, or None where no step can be formed. A
    candidate that does not raise the cost (with ``strict``: that lowers it) is kept by
    ``accept(cost, new_cost)``, which makes it the state and returns True where the solve has
    converged (it ends); otherwise the damping grows and, with ``retry``, the step is formed
    again from the same linearization (without, the iteration ends there: the next one
    linearizes again, and ``iterations`` counts tries). ``damping``: default ``Damping(1e-4)``."""
    damping = Damping(1e-4) if damping is None else damping
    res = LMResult(cost)
    for _ in range(iterations):
        lin = linearize(damping.lam)
        while True:
            new = propose(lin, damping.lam)
            if new is None:
                damping.failed()
                res.rejected += 1
            elif (new < res.cost) if strict else (new <= res.cost):
                converged = accept(res.cost, new)
                res.cost = new
                res.accepted += 1
                damping.accepted()
                if converged:
                    return res
                break
            else:
                damping.rejected()
                res.rejected += 1
            if damping.exhausted or not retry:
                break
        if damping.exhausted:
            break
    return res


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
