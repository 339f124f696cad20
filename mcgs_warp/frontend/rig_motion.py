"""A rig's metric motion between two frames from 2D-2D keypoint matches alone (no 3D points).

Where a rig's cameras overlap only at their edges (a surround car rig: nuScenes, Waymo's side
cameras), few keypoints have stereo depth, so at a low frame rate the 2D-3D PnP of
:mod:`.pnp` has nothing to stand on. The matches still carry the metric motion: a point seen
by camera A at one time and by camera B at the other (the few overlapping pixels, and what
moves from one camera's view into its neighbour's as the rig drives) lies on two rays whose
offset includes the known lever arm between A and B (the generalized epipolar constraint of a
multi-camera rig, Pless 2003; scale observability: Clipp et al. 2008, Kneip & Li 2014).
Matches within one camera give the rotation and the direction of travel only (for a pure
translation their lever arms cancel), so the scale rests on the cross-camera matches; where
they do not determine it, the result is None, never a guess.

Steps: (1) each camera of frame b matched against its own and its overlapping cameras of frame
a (mutual, ratio test); (2) a hypothesis of rotation and direction of travel from each camera's
essential matrix of its same-camera matches (RANSAC on normalized coordinates), completed by
(3) the step length that fits the cross-camera matches best (truncated angular errors over
lengths from 1 cm to 100 m) and (4) a two-view bundle adjustment of the 6-DoF motion and one
inverse depth per match (angular residuals, Huber; its information gives the covariance); the
hypothesis that explains the most matches wins; (5) the length again from its cross-camera
inliers alone, with its standard deviation from the curvature of their cost. Poses: ``T_a_b``
maps frame b's body into frame a's (DESIGN.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import se3_exp
from ..rig import Rig
from .keypoints import ViewKeypoints, mutual_matches, triangulate

MIN_CROSS = 6  # cross-camera inliers below this do not measure a scale
MAX_SCALE_STD = 0.1  # relative standard deviation of the step length above which it is unobserved


@dataclass
class RigMotion:
    T_a_b: np.ndarray  # [4,4] frame b's rig body in frame a's
    matches: np.ndarray  # [M,4] inliers: (camera in a, index in a, camera in b, index in b)
    cov: np.ndarray  # [6,6] covariance of the right perturbation (rho, phi) of T_a_b
    scale_std: float  # relative standard deviation of the step length
    cross: int  # inliers between different cameras (what carries the scale)


def rig_motion(views_a: list[ViewKeypoints], views_b: list[ViewKeypoints], rig: Rig, partners, ratio: float = 0.8, inlier_rad: float = 0.004, min_inliers: int = 20) -> RigMotion | None:
    """The motion ``T_a_b`` between rig frames a and b from their keypoints (``partners[c]``:
    the cameras of frame a that camera c of frame b is matched against, itself first), or None
    when the matches do not determine it (too few inliers, or too few cross-camera ones to fix
    the scale). ``inlier_rad``: inlier threshold, an angle between bearings."""
    import cv2

    if all(list(p) == [c] for c, p in enumerate(partners)):
        return None  # no camera is matched against another: nothing can measure the length
    T_b_c = np.stack([c.T_b_c for c in rig.cameras])
    rows = []
    for cb, vb in enumerate(views_b):
        for ca in partners[cb]:
            va = views_a[ca]
            if len(va) < 2 or len(vb) < 2:
                continue
            m = mutual_matches(va.desc, vb.desc, ratio)
            rows.append(np.stack([np.full(len(m), ca), m[:, 0], np.full(len(m), cb), m[:, 1]], 1))
    M = np.concatenate(rows).astype(np.int64) if rows else np.zeros((0, 4), np.int64)
    if len(M) < min_inliers:
        return None
    fa = np.stack([views_a[c].bearings[i] for c, i in M[:, :2]])
    fb = np.stack([views_b[c].bearings[i] for c, i in M[:, 2:]])
    same = M[:, 0] == M[:, 2]
    cross = np.nonzero(~same)[0]
    if len(cross) < MIN_CROSS:
        return None
    # (2) a hypothesis of rotation and direction from each camera's essential matrix (a façade
    # filling one camera is a plane, whose two-fold ambiguity one camera cannot resolve), each
    # completed by (3) and (4); the one that explains the most matches of every camera wins
    best = None
    for c in range(len(rig)):
        sel = np.nonzero(same & (M[:, 0] == c) & (fa[:, 2] > 0.1) & (fb[:, 2] > 0.1))[0]
        if len(sel) < max(8, min_inliers // 2):
            continue
        pa, pb = fa[sel, :2] / fa[sel, 2:], fb[sel, :2] / fb[sel, 2:]
        Es, mask = cv2.findEssentialMat(pa, pb, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=inlier_rad)
        if Es is None or Es.shape[1:] != (3,) or Es.shape[0] % 3:
            continue
        for E in Es.reshape(-1, 3, 3):  # the five-point solver can leave several
            _n, R_cb_ca, t_cb_ca, _mask = cv2.recoverPose(E, pa, pb, np.eye(3), mask=mask.copy())
            T_cb_ca = np.eye(4)
            T_cb_ca[:3, :3], T_cb_ca[:3, 3] = R_cb_ca, t_cb_ca[:, 0]
            T0 = T_b_c[c] @ np.linalg.inv(T_cb_ca) @ np.linalg.inv(T_b_c[c])  # unit-length camera step
            found = _complete(T0, T_b_c[c][:3, 3], M, fa, fb, cross, T_b_c, inlier_rad, min_inliers)
            if found is not None and (best is None or (found[1].sum(), -found[2]) > (best[1].sum(), -best[2])):
                best = found
    if best is None:
        return None
    T, keep, _cost, cov = best
    n_cross = int((keep & ~same).sum())
    # (5) the length from the cross-camera inliers alone, along the adjusted direction: the
    # same-camera matches outnumber them and, through the rotation's small lever effect, pulled
    # the length 12-62 % off on a rendered street where the cross-camera matches' own optimum
    # was 4-5 % off; the curvature of their cost says how well the length is known
    if n_cross < MIN_CROSS:
        return None
    profile = _length_profile(T, M[keep & ~same], fa[keep & ~same], fb[keep & ~same], T_b_c, 2.0 * inlier_rad)
    if profile is None:
        return None
    f, scale_std = profile
    if not np.isfinite(scale_std) or scale_std > MAX_SCALE_STD:
        return None
    T = T.copy()
    T[:3, 3] *= f
    length = float(np.linalg.norm(T[:3, 3]))
    dirn = T[:3, :3].T @ T[:3, 3] / max(length, 1e-12)  # the step along rho = R^T dt
    # the covariance along the length becomes the profile's (the adjustment's own said what all
    # matches, same-camera ones included, claim about it), its correlations scaled with it
    ba_std = float(np.sqrt(max(dirn @ cov[:3, :3] @ dirn, 1e-30)))
    D = np.eye(6)
    D[:3, :3] += (scale_std * length / ba_std - 1.0) * np.outer(dirn, dirn)
    cov = D @ cov @ D.T
    return RigMotion(T, M[keep], cov, scale_std, n_cross)


def _complete(T0, centre, M, fa, fb, cross, T_b_c, inlier_rad, min_inliers):
    """A hypothesis ``T0`` (rotation, and the camera at ``centre`` moved by a unit step) made
    metric: (3) the step length from the cross-camera matches' angular errors (what the length
    changes: the lever arms between cameras are metric), truncated at twice the inlier
    threshold, least over lengths from 1 cm to 100 m; (4) the two-view bundle adjustment, on all
    matches (Huber), then twice on the inliers. Returns (T, inlier mask, robust cost per
    inlier, covariance) or None."""
    R = T0[:3, :3]
    lever = (np.eye(3) - R) @ centre  # the body moves by t = s u + lever
    u = T0[:3, 3] - lever

    def at(length):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, length * u + lever
        return T

    lengths = np.geomspace(0.01, 100.0, 321)  # 3 % apart
    cost = [np.sum(np.minimum(_angular_error(at(s), M[cross], fa[cross], fb[cross], T_b_c), 2.0 * inlier_rad) ** 2) for s in lengths]
    T = at(float(lengths[int(np.argmin(cost))]))
    keep = np.ones(len(M), bool)
    for _ in range(3):
        sol = _two_view_ba(T, M[keep], fa[keep], fb[keep], T_b_c, inlier_rad)
        if sol is None:
            return None
        T, cov = sol[0], sol[2]
        err = _angular_error(T, M, fa, fb, T_b_c)
        keep = err < 2.0 * inlier_rad
        if keep.sum() < min_inliers:
            return None
    return T, keep, float(np.mean(err[keep] ** 2)), cov


def _length_profile(T, M, fa, fb, T_b_c, cap):
    """The factor ``f`` on ``T``'s translation that the matches ``M`` fit best (the sum of their
    squared angular errors, each capped at ``cap``), searched from 0.5 to 2 in 0.9 % steps and
    refined by a parabola through that cost near its least, and the relative standard deviation
    of the length: the parabola's curvature with the noise variance from the fit's own residuals
    (the least cost over its degrees of freedom, one per match once its depth is triangulated;
    the keypoints' nominal noise made a rendered street's steps 7x overconfident). None where
    the least is at the search's edge or the cost does not curve up."""
    factors = np.geomspace(0.5, 2.0, 161)
    cost = []
    for f in factors:
        Tf = T.copy()
        Tf[:3, 3] *= f
        cost.append(np.sum(np.minimum(_angular_error(Tf, M, fa, fb, T_b_c), cap) ** 2))
    cost = np.asarray(cost)
    i = int(np.argmin(cost))
    if i == 0 or i == len(factors) - 1 or len(M) < 3:
        return None
    near = np.nonzero(np.abs(np.log(factors / factors[i])) <= 0.05)[0]  # within 5 % of the least: a quadratic there
    a, b, c = np.polyfit(np.log(factors[near]), cost[near], 2)
    if a <= 0:
        return None
    x0 = -b / (2 * a)  # log f at the vertex
    if abs(x0 - np.log(factors[i])) > 0.05:
        return None
    sigma2 = max(c - b * b / (4 * a), 1e-30) / (len(M) - 1)  # least cost / (matches - the length)
    return float(np.exp(x0)), float(np.sqrt(sigma2 / a))  # cost / sigma2 = (x - x0)^2 / std^2 + const, x = log f


def _points_b(T: np.ndarray, rho: np.ndarray, M: np.ndarray, fa: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """Each match's point, at inverse depth ``rho`` along its bearing in camera M[:,0] of frame a,
    in camera M[:,2] of frame b [N,3]."""
    Xa = np.einsum("nij,nj->ni", T_b_c[M[:, 0], :3, :3], fa / rho[:, None]) + T_b_c[M[:, 0], :3, 3]
    Xb = (Xa - T[:3, 3]) @ T[:3, :3]
    return np.einsum("nji,nj->ni", T_b_c[M[:, 2], :3, :3], Xb - T_b_c[M[:, 2], :3, 3])


def _angular_error(T, M, fa, fb, T_b_c) -> np.ndarray:
    """Angle (rad) between each match's bearing in b and its point triangulated with ``T`` (inf: behind or parallel)."""
    rho = _depths(T, M, fa, fb, T_b_c)
    ok = np.isfinite(rho)
    X = _points_b(T, np.where(ok, rho, 1.0), M, fa, T_b_c)
    cosang = np.einsum("ni,ni->n", X, fb) / np.maximum(np.linalg.norm(X, axis=1), 1e-12)
    return np.where(ok, np.arccos(np.clip(cosang, -1.0, 1.0)), np.inf)


def _depths(T, M, fa, fb, T_b_c) -> np.ndarray:
    """Inverse depth along each match's unit bearing in a, midpoint-triangulated (NaN: behind or parallel)."""
    T_c_b = np.linalg.inv(T_b_c)
    _X, s, r = triangulate(T_c_b[M[:, 0]] @ T @ T_b_c[M[:, 2]], fa, fb)  # T_ca_cb per match
    ok = (s > 0) & (r > 0) & np.isfinite(s)
    return np.where(ok, 1.0 / np.where(ok, s, 1.0), np.nan)


def _two_view_ba(T0, M, fa, fb, T_b_c, inlier_rad, iterations: int = 30):
    """Damped Gauss-Newton (Levenberg-Marquardt's schedule, :mod:`~mcgs_warp.ba.lm`) over the right perturbation of ``T0`` (rho, phi) and one inverse
    depth per match along its bearing in a, the depths eliminated by the Schur complement
    (each is in its own 3 residuals): residuals are the unit bearing in b minus the normalized
    point there (about an angle), Huber at ``inlier_rad`` (reweighted). The step length is
    coupled with every depth, which a generic trust-region solver crawls along; the reduced
    6x6 system moves it in one step. Returns (T, inverse depths, the motion's covariance
    [6,6] from the reduced information, the residual variance) or None."""
    from ..ba.lm import damped_step, minimize

    rho = _depths(T0, M, fa, fb, T_b_c)
    good = np.isfinite(rho) & (rho > 0)
    if good.sum() < 8:
        return None
    M, fa, fb, rho = M[good], fa[good], fb[good], rho[good]

    def residual(T, rho):
        X = _points_b(T, rho, M, fa, T_b_c)
        return X / np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-12) - fb  # [N,3]

    def robust_cost(r):
        e = np.linalg.norm(r, axis=1)
        return float(np.sum(np.where(e <= inlier_rad, e * e, 2 * inlier_rad * e - inlier_rad**2)))

    def linearize(T, rho, eps=1e-6):
        r = residual(T, rho)
        Jp = np.stack([(residual(T @ se3_exp(eps * np.eye(6)[j]), rho) - r) / eps for j in range(6)], 2)  # [N,3,6]
        h = np.maximum(1e-6 * rho, 1e-9)
        Jd = (residual(T, rho + h) - r) / h[:, None]  # [N,3]
        e = np.linalg.norm(r, axis=1)
        w = np.where(e <= inlier_rad, 1.0, inlier_rad / np.maximum(e, 1e-18))  # Huber's IRLS weight
        Hpp = np.einsum("n,nip,niq->pq", w, Jp, Jp)
        Hpd = np.einsum("n,nip,ni->np", w, Jp, Jd)
        Hdd = np.einsum("n,ni,ni->n", w, Jd, Jd)
        gp = np.einsum("n,nip,ni->p", w, Jp, r)
        gd = np.einsum("n,ni,ni->n", w, Jd, r)
        return Hpp, Hpd, Hdd, gp, gd

    T, cand = T0, None

    def propose(lin, lam):
        nonlocal cand
        Hpp, Hpd, Hdd, gp, gd = lin
        Dd = Hdd * (1 + lam) + 1e-12
        dp = damped_step((Hpp - (Hpd / Dd[:, None]).T @ Hpd), -(gp - Hpd.T @ (gd / Dd)), np.arange(6), lam)
        if not np.all(np.isfinite(dp)):
            return None
        dd = -(gd + Hpd @ dp) / Dd
        cand = T @ se3_exp(dp), np.maximum(rho + dd, 1e-4)
        return robust_cost(residual(*cand))

    def accept(cur, c):
        nonlocal T, rho
        T, rho = cand
        return cur - c < 1e-10 * max(cur, 1e-30)

    minimize(robust_cost(residual(T0, rho)), lambda lam: linearize(T, rho), propose, accept, iterations)
    Hpp, Hpd, Hdd, _, _ = linearize(T, rho)
    S = Hpp - (Hpd / np.maximum(Hdd, 1e-18)[:, None]).T @ Hpd
    r = residual(T, rho)
    sigma2 = float(np.median(np.sum(r * r, 1)) / 1.386)  # per bearing component, robust (median of chi2 with 2 dof)
    try:
        cov = sigma2 * np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return None
    return T, rho, cov, sigma2
