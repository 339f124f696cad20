"""Multi-camera PnP: the rig pose ``T_w_b`` from 2D-3D matches seen by any of its cameras.

Every camera's matches count together, in the body frame: RANSAC draws a minimal sample of
three matches from one camera (chosen in proportion to its match count), solves P3P for that
camera (OpenCV's solver, in a virtual pinhole turned towards the sample, so fisheye and
equirectangular bearings work as well as pinhole ones), turns the camera pose into a rig
pose through ``T_b_c`` and scores it on the matches of *all* cameras. The caller's guess
(constant velocity) is scored as one more hypothesis, so it wins where the matches do not
agree on anything better. The best hypothesis is then refined by Levenberg-Marquardt on all
its inliers (robust Huber cost, bearing residuals), the inliers re-counted and refined once more. Errors are
angles between the observed and the predicted bearing, so thresholds mean the same at any
resolution (as OpenGV's central/non-central absolute-pose methods do).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..ba.lm import Damping, minimize
from ..geometry import invert, se3_exp
from ..rig import Rig


@dataclass
class RigObservations:
    """Matches of one camera: observed unit bearings [M,3] (camera frame) and world points [M,3] (m)."""

    camera: int
    bearings: np.ndarray
    points_w: np.ndarray


@dataclass
class PnPResult:
    T_w_b: np.ndarray  # [4,4] rig pose (body -> world)
    inliers: list = field(default_factory=list)  # per observation set: [M] bool
    n_inliers: int = 0
    n_matches: int = 0
    from_guess: bool = False  # the guess beat every RANSAC hypothesis
    matches: np.ndarray | None = None  # the caller's record of which matches were inliers (KeypointTracker.localize)

    @property
    def inlier_ratio(self) -> float:
        return self.n_inliers / max(self.n_matches, 1)


def _virtual_rotation(bearings: np.ndarray) -> np.ndarray | None:
    """A rotation R [3,3] taking the mean of ``bearings`` [3,3] to +z (None if they span too wide)."""
    m = bearings.mean(0)
    n = np.linalg.norm(m)
    if n < 1e-6:
        return None
    z = m / n
    a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: new axes in the old frame
    if (bearings @ R.T)[:, 2].min() < 0.2:  # beyond ~78 degrees from the axis
        return None
    return R


def p3p(bearings: np.ndarray, points: np.ndarray) -> list[np.ndarray]:
    """Camera poses ``T_c_w`` [4,4] (up to four) from three bearings [3,3] and world points [3,3]."""
    import cv2

    R_v = _virtual_rotation(bearings)
    if R_v is None:
        return []
    b = bearings @ R_v.T
    img = (b[:, :2] / b[:, 2:3]).astype(np.float64)
    try:
        n, rvecs, tvecs = cv2.solveP3P(points.astype(np.float64), img, np.eye(3), None, flags=cv2.SOLVEPNP_P3P)
    except cv2.error:
        return []
    out = []
    for rv, tv in zip(rvecs[:n] if n else [], tvecs[:n] if n else []):
        T_v_w = np.eye(4)
        T_v_w[:3, :3] = cv2.Rodrigues(rv)[0]
        T_v_w[:3, 3] = np.ravel(tv)
        T = np.eye(4)
        T[:3, :3] = R_v.T
        out.append(T @ T_v_w)
    return out


class RigPnP:
    """RANSAC + LM absolute pose of a rig (module docstring). ``inlier_rad``: angle between
    observed and predicted bearing of an inlier."""

    def __init__(self, rig: Rig, inlier_rad: float = 0.004, iterations: int = 300, confidence: float = 0.999, seed: int = 0):
        self.T_b_c = np.stack([c.T_b_c for c in rig.cameras])
        self.T_c_b = np.stack([invert(T) for T in self.T_b_c])
        self.inlier_rad, self.iterations, self.confidence, self.seed = inlier_rad, iterations, confidence, seed

    def errors(self, T_w_b: np.ndarray, obs: list[RigObservations]) -> list[np.ndarray]:
        """Per observation set: angle [M] (rad) between observed and predicted bearings (pi behind the camera)."""
        T_b_w = invert(T_w_b)
        out = []
        for o in obs:
            T_c_w = self.T_c_b[o.camera] @ T_b_w
            X = o.points_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]
            n = np.linalg.norm(X, axis=1)
            cosang = np.einsum("ij,ij->i", X, o.bearings) / np.maximum(n, 1e-12)
            out.append(np.arccos(np.clip(cosang, -1.0, 1.0)))
        return out

    def _score(self, T_w_b, obs) -> tuple[int, list]:
        inl = [e < self.inlier_rad for e in self.errors(T_w_b, obs)]
        return int(sum(int(m.sum()) for m in inl)), inl

    def solve(self, obs: list[RigObservations], guess: np.ndarray | None = None, min_inliers: int = 12) -> PnPResult | None:
        """The rig pose from ``obs`` (sets of matches, one per camera; a set may be empty),
        or None when no hypothesis gathers ``min_inliers`` inliers. The result's ``inliers``
        follow ``obs`` set by set."""
        total = sum(len(o.bearings) for o in obs)
        if total < max(min_inliers, 3):
            return None
        counts = np.array([len(o.bearings) for o in obs], np.float64)
        usable = counts >= 3
        best_T, best_n, best_inl, from_guess = None, -1, None, False
        if guess is not None:
            best_n, best_inl = self._score(guess, obs)
            best_T, from_guess = guess, True
        if usable.any():
            rng = np.random.default_rng((self.seed, total))  # the same matches draw the same samples (a resumed run repeats itself)
            p = np.where(usable, counts, 0.0) / counts[usable].sum()
            needed, it = self.iterations, 0
            while it < min(needed, self.iterations):
                it += 1
                k = int(rng.choice(len(obs), p=p))
                o = obs[k]
                pick = rng.choice(len(o.bearings), 3, replace=False)
                for T_c_w in p3p(o.bearings[pick], o.points_w[pick]):
                    T_w_b = invert(T_c_w) @ self.T_c_b[o.camera]
                    n, inl = self._score(T_w_b, obs)
                    if n > best_n:
                        best_T, best_n, best_inl, from_guess = T_w_b, n, inl, False
                        w = max(n / total, 1e-3)
                        needed = int(np.ceil(np.log(1 - self.confidence) / np.log(max(1 - w**3, 1e-12))))
        if best_T is None or best_n < min_inliers:
            return None
        T, inl = best_T, best_inl
        for _ in range(2):  # refine on the consensus, re-count it, refine on the new one
            T = self.refine(T, obs, inl)
            n, inl = self._score(T, obs)
        if n < min_inliers:
            return None
        return PnPResult(T, inl, n, total, from_guess)

    def refine(self, T_w_b: np.ndarray, obs: list[RigObservations], inliers: list, iterations: int = 10) -> np.ndarray:
        """Levenberg-Marquardt (:func:`~mcgs_warp.ba.lm.minimize`; a step kept only if the cost falls) with
        Huber weights on the bearing residuals of ``inliers`` (unit-vector differences, about the
        angle at these sizes; threshold ``inlier_rad``); increments right-multiplied in the body
        frame (DESIGN.md)."""
        sets = [(o.camera, o.bearings[m], o.points_w[m]) for o, m in zip(obs, inliers) if m.any()]
        if sum(len(b) for _, b, _ in sets) < 6:
            return T_w_b
        T, cand, dx = T_w_b.copy(), None, None

        def linearize(lam):
            H, g = np.zeros((6, 6)), np.zeros(6)
            for c, b, X_w in sets:
                r, J, w = self._linearize(T, c, b, X_w)
                H += np.einsum("n,nki,nkj->ij", w, J, J)
                g += np.einsum("n,nki,nk->i", w, J, r)
            return H, g

        def propose(lin, lam):
            nonlocal cand, dx
            H, g = lin
            try:
                dx = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-9), g)
            except np.linalg.LinAlgError:
                return None
            cand = T @ se3_exp(dx)
            return self._cost(cand, sets)

        def accept(cost, new):
            nonlocal T
            T = cand
            return np.linalg.norm(dx) < 1e-9

        # its own schedule: x0.3 on a kept step, x10 on a refused one, and a system it cannot
        # solve or a damping past 1e4 ends it; each try is one of the ``iterations``
        damping = Damping(1e-4, up=10.0, down=(0.3, 1.0), fail=math.inf, lo=0.0, hi=1e4)
        minimize(self._cost(T, sets), linearize, propose, accept, iterations, damping, strict=True, retry=False)
        return T

    def _residual(self, T_w_b, c, b, X_w):
        T_c_w = self.T_c_b[c] @ invert(T_w_b)
        X = X_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        n = np.linalg.norm(X, axis=1, keepdims=True)
        return X / np.maximum(n, 1e-12) - b, X, n

    def _cost(self, T, sets) -> float:
        d = self.inlier_rad
        total = 0.0
        for c, b, X_w in sets:
            e = np.linalg.norm(self._residual(T, c, b, X_w)[0], axis=1)
            total += float(np.where(e <= d, 0.5 * e * e, d * (e - 0.5 * d)).sum())
        return total

    def _linearize(self, T_w_b, c, b, X_w):
        """Residuals [n,3], their Jacobian [n,3,6] w.r.t. the body increment and Huber weights [n]."""
        r, X_c, n = self._residual(T_w_b, c, b, X_w)
        u = X_c / np.maximum(n, 1e-12)
        # d(unit vector)/d(X_c) = (I - u u^T) / |X_c|
        P = (np.eye(3)[None] - u[:, :, None] * u[:, None, :]) / n[:, :, None]
        # X_c = R_cb (X_b) + t_cb with X_b = T_b_w X_w; body increment: X_b <- Exp(-xi) X_b,
        # so dX_b/d(rho, phi) = [-I, [X_b]x]
        T_b_w = invert(T_w_b)
        X_b = X_w @ T_b_w[:3, :3].T + T_b_w[:3, 3]
        R_cb = self.T_c_b[c][:3, :3]
        dXb = np.zeros((len(X_b), 3, 6))
        dXb[:, :, :3] = -np.eye(3)
        dXb[:, 0, 4], dXb[:, 0, 5] = -X_b[:, 2], X_b[:, 1]
        dXb[:, 1, 3], dXb[:, 1, 5] = X_b[:, 2], -X_b[:, 0]
        dXb[:, 2, 3], dXb[:, 2, 4] = -X_b[:, 1], X_b[:, 0]
        J = P @ (R_cb[None] @ dXb)
        e = np.linalg.norm(r, axis=1)
        w = np.where(e <= self.inlier_rad, 1.0, self.inlier_rad / np.maximum(e, 1e-12))
        return r, J, w
