"""Sensor-depth alignment factors in MCBA: a textureless wall with good depth still tracks.

With exact sensor depth every grid pixel of a source view (i, ci) is a known 3D point. Moved
into a target view (j, cj) by the current poses it predicts an inverse depth there; the
residual is its difference from the target's own sensor inverse depth at the pixel it lands
on (bilinear on the reduced grid; pixels next to a depth edge are skipped):

    r = 1 / depth_cj(T_cj_ci X_ci) - rho_j(Pi_cj(T_cj_ci X_ci))

a 2.5D ICP residual (as DVO-SLAM's and KinectFusion's depth terms), weighted by
``weight`` (the unit of MCBA's inverse-depth prior, px^2 m^2: small beside the photometric
correspondences where there is texture, alone where there is none), robust (Huber, the same
threshold), on the poses only (exact depth is not re-estimated). Its Jacobian includes the
target depth's gradient through the projection. NumPy, float64, added to MCBA's reduced
camera system like :mod:`.keypoint_factors`.

Samples are evaluated ``CHUNK`` at a time, and each run of one keyframe pair's samples is summed
by one matrix product before it enters the system: global BA gives these factors every edge
of the run (millions of samples), whose [n,12,12] outer products and [n,4,4] pose copies at
once were the offline stage's memory peak (the 160-frame room loop: 3.8 GB, 1.2 GB in chunks)
and whose per-sample ``np.add.at`` was slow.
"""

from __future__ import annotations

import numpy as np

from .keypoint_factors import _skew, project_by_camera

EDGE_REL = 0.1  # a target pixel whose 2x2 grid neighbours differ by more than this share in inverse depth straddles a depth edge
CHUNK = 1 << 14  # samples evaluated at once: bounds the temporaries (a few MB of [CHUNK,4,4] and [CHUNK,12] float64)


class DepthAlignmentFactors:
    """Pose-only factors between views with sensor depth (module docstring).

    ``edges`` [E,>=4] ``(slot i, camera ci, slot j, camera cj)`` (i != j); ``depth`` [n,C,h,w]
    sensor depth on the reduced grid of the window's slots (m, 0 = none); ``rays`` [C,h,w,3]
    the grid's unit-depth rays; ``cameras`` the reduced-grid cameras (Warp structs);
    ``T_b_c`` [C,4,4]; ``step``: use every step-th grid pixel."""

    def __init__(self, edges, depth, rays, cameras, T_b_c, weight: float, huber_delta: float, step: int = 2):
        self.cams, self.T_b_c, self.w, self.delta = cameras, T_b_c, weight, huber_delta
        self.depth = depth
        with np.errstate(divide="ignore"):
            self.rho = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-12), 0.0)
        src = []
        for i, ci, j, cj in np.asarray(edges)[:, :4].tolist():
            d = depth[i, ci, ::step, ::step]
            ys, xs = np.nonzero(d > 0)
            ys, xs = ys * step, xs * step
            if len(ys):
                src.append((np.full(len(ys), i), np.full(len(ys), ci), np.full(len(ys), j), np.full(len(ys), cj), ys, xs, rays[ci, ys, xs] * depth[i, ci, ys, xs][:, None]))
        self.step = step
        if src:
            self.si, self.ci, self.sj, self.cj, self.ys, self.xs = (np.concatenate([s[k] for s in src]).astype(int) for k in range(6))
            self.X_ci = np.concatenate([s[6] for s in src]).astype(np.float64)
        else:
            self.si = self.ci = self.sj = self.cj = self.ys = self.xs = np.zeros(0, int)
            self.X_ci = np.zeros((0, 3))

    def __len__(self) -> int:
        return len(self.si)

    def _chunks(self) -> list:
        """Slices of at most ``CHUNK`` samples covering them all, in order."""
        return [slice(a, min(a + CHUNK, len(self))) for a in range(0, len(self), CHUNK)]

    def _points(self, poses, sl: slice):
        """The samples ``sl``'s points in body i, body j and camera j."""
        Tbc_i, Twb_i, Twb_j, Tbc_j = self.T_b_c[self.ci[sl]], poses[self.si[sl]], poses[self.sj[sl]], self.T_b_c[self.cj[sl]]
        X_bi = np.einsum("nij,nj->ni", Tbc_i[:, :3, :3], self.X_ci[sl]) + Tbc_i[:, :3, 3]
        X_w = np.einsum("nij,nj->ni", Twb_i[:, :3, :3], X_bi) + Twb_i[:, :3, 3]
        X_bj = np.einsum("nji,nj->ni", Twb_j[:, :3, :3], X_w - Twb_j[:, :3, 3])
        X_cj = np.einsum("nji,nj->ni", Tbc_j[:, :3, :3], X_bj - Tbc_j[:, :3, 3])
        return X_bi, X_bj, X_cj

    def _lookup(self, X_cj, jac: bool, sl: slice):
        """Of the samples ``sl`` (points ``X_cj`` [n,3]): predicted inverse depth, target inverse
        depth (bilinear), its gradient [n,2] and the projection Jacobian [n,2,3] on the reduced
        grid; valid [n]."""
        n = len(X_cj)
        uv, J, valid, X = project_by_camera(self.cams, self.cj[sl], X_cj, jac)
        equi = np.array([cam.model == 2 for cam in self.cams])[self.cj[sl]]  # equirectangular: depth is the ray length
        r = np.linalg.norm(X, axis=1)
        pred = np.where(equi, 1.0 / r, 1.0 / X[:, 2])
        dpred = np.where(equi[:, None], -X / r[:, None] ** 3, np.stack([np.zeros(n), np.zeros(n), -1.0 / X[:, 2] ** 2], 1))
        h, w = self.rho.shape[2:]
        x0, y0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = valid & (x0 >= 0) & (y0 >= 0) & (x0 < w - 1) & (y0 < h - 1) & np.isfinite(uv).all(1)
        x0, y0 = np.where(inside, x0, 0), np.where(inside, y0, 0)
        fx, fy = uv[:, 0] - x0, uv[:, 1] - y0
        R, sj, cj = self.rho, self.sj[sl], self.cj[sl]  # corners indexed directly: no [n,h,w] copy
        r00, r01, r10, r11 = R[sj, cj, y0, x0], R[sj, cj, y0, x0 + 1], R[sj, cj, y0 + 1, x0], R[sj, cj, y0 + 1, x0 + 1]
        corners = np.stack([r00, r01, r10, r11], 1)
        smooth = (corners.min(1) > 0) & (corners.max(1) - corners.min(1) < EDGE_REL * corners.max(1))
        target = (1 - fy) * ((1 - fx) * r00 + fx * r01) + fy * ((1 - fx) * r10 + fx * r11)
        grad = np.stack([(1 - fy) * (r01 - r00) + fy * (r11 - r10), (1 - fx) * (r10 - r00) + fx * (r11 - r01)], 1)
        return pred, target, dpred, grad, J, inside & smooth

    def residuals(self, poses):
        """Residuals [n] and valid [n] of every sample."""
        return self._residuals(poses)[:2]

    def _residuals(self, poses):
        """Residuals [n], valid [n] and predicted inverse depths [n], ``CHUNK`` samples at a time."""
        r, valid, pred = np.zeros(len(self)), np.zeros(len(self), bool), np.zeros(len(self))
        for sl in self._chunks():
            pred[sl], target, _, _, _, valid[sl] = self._lookup(self._points(poses, sl)[2], False, sl)
            r[sl] = pred[sl] - target
        return r, valid, pred

    def _robust(self, r, valid):
        s = np.sqrt(self.w) * np.abs(r)
        cost = np.where(s <= self.delta, 0.5 * s * s, self.delta * (s - 0.5 * self.delta))
        W = self.w * np.where(s <= self.delta, 1.0, self.delta / np.maximum(s, 1e-300))
        return np.where(valid, cost, 0.0), np.where(valid, W, 0.0)

    def noise(self, _poses=None):
        """None: ``weight`` is in the dense class's units (as the depth prior's), so it keeps
        its weight relative to the dense class (:mod:`.variance`)."""
        return None

    def cost(self, poses, _disp=None) -> float:
        r, valid = self.residuals(poses)
        return float(self._robust(r, valid)[0].sum())

    def agreement(self, poses, slot: int, rel: float = 0.02, min_share: float = 0.5, min_conditioning: float = 1e-4) -> np.ndarray:
        """[n] bool: the samples of view slot ``slot`` whose moved depth agrees with the
        target's within ``rel`` (relative inverse depth), or none at all when they do not
        place the slot: fewer than ``min_share`` of its valid samples agree (a wrong pose
        where only the floor agrees), or their information leaves a direction free (one
        plane fixes only three of the six; eigenvalues of the pose block below
        ``min_conditioning`` of the largest, translation in units of the mean depth)."""
        r, valid, pred = self._residuals(poses)
        mine = valid & (self.si == slot)
        ok = mine & (np.abs(r) <= rel * np.abs(pred))
        if not mine.any() or ok.sum() < min_share * mine.sum():
            return np.zeros(len(r), bool)
        S = self.reduced_terms(poses, 0.0)[0][6 * slot : 6 * slot + 6, 6 * slot : 6 * slot + 6]
        depth = float(np.median(np.linalg.norm(self.X_ci[mine], axis=1)))
        D = np.diag([depth] * 3 + [1.0] * 3)  # translation per metre of depth ~ rotation per radian
        ev = np.linalg.eigvalsh(D @ S @ D)
        if ev[-1] <= 0 or ev[0] < min_conditioning * ev[-1]:
            return np.zeros(len(r), bool)
        return ok

    def reduced_terms(self, poses, lam: float):
        """``S`` [6n,6n] and ``rhs`` [6n] of these pose-only factors (MCBA's sign convention),
        ``CHUNK`` samples at a time; the samples come edge by edge, so each run of one keyframe
        pair is one [12,12] product added to ``S``."""
        n = len(poses)
        S = np.zeros((6 * n, 6 * n))
        rhs = np.zeros(6 * n)
        for sl in self._chunks():
            si, sj = self.si[sl], self.sj[sl]
            X_bi, X_bj, X_cj = self._points(poses, sl)
            pred, target, dpred, grad, Jp, valid = self._lookup(X_cj, True, sl)
            r = pred - target
            _, W = self._robust(r, valid)
            g = dpred - np.einsum("nk,nkj->nj", grad, Jp)  # d r / d X_cj
            R_cj_b = np.transpose(self.T_b_c[self.cj[sl]][:, :3, :3], (0, 2, 1))
            R_bj_w = np.transpose(poses[sj][:, :3, :3], (0, 2, 1))
            R_w_bi = poses[si][:, :3, :3]
            a_j = np.einsum("nj,nji->ni", g, R_cj_b)  # d r / d X_bj
            a_w = np.einsum("nj,nji->ni", a_j, R_bj_w)  # d r / d X_w
            eye = np.broadcast_to(np.eye(3), (len(r), 3, 3))
            J_i = np.einsum("nj,nji->ni", np.einsum("nj,nji->ni", a_w, R_w_bi), np.concatenate([eye, -_skew(X_bi)], axis=2))
            J_j = np.einsum("nj,nji->ni", a_j, np.concatenate([-eye, _skew(X_bj)], axis=2))
            A = np.concatenate([J_i, J_j], axis=1)  # [m,12]
            runs = np.flatnonzero(np.concatenate([[True], (si[1:] != si[:-1]) | (sj[1:] != sj[:-1])]))  # first sample of each run of one pair
            WA = W[:, None] * A
            blocks = np.stack([WA[a:b].T @ A[a:b] for a, b in zip(runs, np.append(runs[1:], len(A)))])  # [runs,12,12]
            grads = np.add.reduceat(-(W * r)[:, None] * A, runs, axis=0)
            idx = np.concatenate([6 * si[runs][:, None] + np.arange(6), 6 * sj[runs][:, None] + np.arange(6)], axis=1)
            np.add.at(S, (idx[:, :, None], idx[:, None, :]), blocks)
            np.add.at(rhs, idx, grads)
        return S, rhs

    def candidate(self, dxi) -> None:  # no variables of its own
        pass

    def accept(self) -> None:
        pass
