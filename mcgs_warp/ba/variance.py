"""Variance components: each MCBA residual class weighted by the noise it measurably carries.

MCBA sums residual classes of different kinds (dense DIS correspondences, keypoint tracks,
the keypoint odometry's motion, sensor-depth alignment). Their nominal weights assume unit
variance in grid pixels; what they really carry differs by class and by sequence (on
synthetic images DIS is nearly exact, on real ones it is not). So each class's variance factor
is estimated from its own residuals (variance component estimation, Förstner 1979; a robust
scale as in IRLS, Triggs et al. 2000) and its information is divided by it:

    sigma2_k = (1.4826 median |z_k|)^2 * n_k / red_k

``z_k`` are the class's whitened residual components (sqrt(weight) * residual), ``n_k`` their
number and ``red_k`` the class's share of the redundancy (observations minus the unknowns it
determines: a dense grid pixel's own inverse depth, a track's point), so that residuals which
the solution absorbs do not look like small noise.

Dense correspondences are also correlated: DIS estimates a grid pixel's flow from patches
that overlap its neighbours', so thousands of them carry the information of far fewer. The
lag-1 correlation ``rho`` of the whitened residual field along grid rows and columns
(:func:`field_correlation`) gives, for a separable exponential (AR(1)) field, the factor by
which the variance of a mean grows over independent samples,

    kappa = ((1 + rho) / (1 - rho))^2        (N_eff = N / kappa)

and the dense class's information is divided by ``kappa * sigma2`` (research note
``residual-weighting.md``, section 3). A class whose information is already in absolute
units (the keypoint odometry's covariance carries its own measured variance,
:meth:`~mcgs_warp.frontend.keypoint_odometry.KeypointOdometry`) is scaled by the dense
class's variance alone: MCBA keeps the dense class (and its depth prior) at weight 1 and
multiplies every other class by the ratio (:func:`class_scales`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAD_TO_SIGMA = 1.4826  # median |z| of a unit normal is 1 / 1.4826
MAX_RHO = 0.95  # correlations beyond this say more about the scene than the noise; kappa <= 1521
SCALE_RANGE = (1e-3, 1e4)  # a class's weight relative to the dense class stays inside this


@dataclass
class ClassNoise:
    """Measured noise of one residual class (``sigma2`` in its whitened units)."""

    n: int  # residual components
    redundancy: float  # n minus the unknowns the class determines
    sigma2: float  # variance factor (1: the nominal weights are right)
    kappa: float = 1.0  # information lost to correlation (N / N_eff)

    @property
    def effective(self) -> float:
        """The variance factor per independent observation: ``kappa * sigma2``."""
        return self.kappa * self.sigma2


def median_abs(z: np.ndarray) -> tuple[int, float]:
    """The number of finite values of ``z`` and the median of their magnitudes (float64, as
    ``np.median(np.abs(z))``), from one copy in ``z``'s own dtype: global BA passes millions."""
    z = np.asarray(z).ravel()
    a = z[np.isfinite(z)]  # a copy, worked on in place
    n = len(a)
    if n == 0:
        return 0, float("nan")
    np.abs(a, out=a)
    k = n // 2
    if n % 2:
        a.partition(k)
        return n, float(a[k])
    a.partition((k - 1, k))
    return n, 0.5 * (float(a[k - 1]) + float(a[k]))


def robust_variance(z: np.ndarray, unknowns: float = 0.0) -> ClassNoise | None:
    """Variance factor of whitened residual components ``z`` [n] whose solution determined
    ``unknowns`` parameters (MAD scale, corrected for the redundancy); None with fewer
    than 10 components left over."""
    n, m = median_abs(z)
    red = n - unknowns
    if n < 10 or red < 10:
        return None
    s = MAD_TO_SIGMA * m
    if not s > 0:
        return None
    return ClassNoise(n, float(red), s * s * n / red)


def field_correlation(res: np.ndarray, valid: np.ndarray, chunk: int = 64) -> float:
    """Lag-1 correlation of a residual field ``res`` [E,h,w,2] (``valid`` [E,h,w] bool) along
    grid rows and columns, pooled over edges and both components, on pairs of valid
    neighbours; residuals beyond 3 robust sigmas are clipped (one outlier makes no
    correlation). 0 when too few pairs. Sums are gathered ``chunk`` edges at a time, so a
    global solve's thousands of edges need no float64 copy of the whole field."""
    res = np.asarray(res)
    valid = np.asarray(valid, bool)
    if int(valid.sum()) < 10:
        return 0.0
    s = MAD_TO_SIGMA * median_abs(res[valid])[1] + 1e-30
    # per direction (along rows, along columns): pairs, then per component sums of x, y, xy, xx, yy
    count = np.zeros(2, np.int64)
    sums = np.zeros((2, 5, res.shape[-1]))
    for e0 in range(0, len(res), chunk):
        r = np.clip(res[e0 : e0 + chunk].astype(np.float64), -3 * s, 3 * s)
        v = valid[e0 : e0 + chunk]
        for d, (a, b, va, vb) in enumerate(((r[:, :, 1:], r[:, :, :-1], v[:, :, 1:], v[:, :, :-1]), (r[:, 1:], r[:, :-1], v[:, 1:], v[:, :-1]))):
            m = va & vb
            x, y = a[m], b[m]
            count[d] += len(x)
            sums[d] += np.stack([x.sum(0), y.sum(0), (x * y).sum(0), (x * x).sum(0), (y * y).sum(0)])
    num = den_a = den_b = 0.0
    for d in range(2):
        if count[d] == 0:
            continue
        sx, sy, sxy, sxx, syy = sums[d]
        num += float((sxy - sx * sy / count[d]).sum())  # about each component's mean
        den_a += float((sxx - sx * sx / count[d]).sum())
        den_b += float((syy - sy * sy / count[d]).sum())
    if count.sum() < 10 or den_a <= 0 or den_b <= 0:
        return 0.0
    return float(num / np.sqrt(den_a * den_b))


def correlation_factor(rho: float) -> float:
    """``kappa = ((1 + rho) / (1 - rho))^2`` of a separable AR(1) field (module docstring);
    negative correlations count as none."""
    rho = float(np.clip(rho, 0.0, MAX_RHO))
    return ((1.0 + rho) / (1.0 - rho)) ** 2


def dense_noise(res: np.ndarray, valid: np.ndarray, sources: np.ndarray, depth_share: float = 1.0) -> ClassNoise | None:
    """Noise of the dense class from its whitened residual field (``res`` [E,h,w,2],
    ``valid`` [E,h,w]) of edges leaving source views ``sources`` [E] (any id per view): each
    source grid pixel with a residual owns one inverse depth, of which the correspondences
    determine ``depth_share`` (less where a depth prior holds it); the correlation from
    :func:`field_correlation`."""
    valid = np.asarray(valid, bool)
    sources = np.asarray(sources)
    noise = robust_variance(np.asarray(res)[valid])
    if noise is None:
        return None
    pixels = sum(float(valid[sources == v].any(axis=0).sum()) for v in np.unique(sources))
    red = noise.n - depth_share * pixels
    if red < 10:
        return None
    noise.sigma2 *= noise.n / red
    noise.redundancy = red
    noise.kappa = correlation_factor(field_correlation(res, valid))
    return noise


def disagreement_factor(S_dense: np.ndarray, rhs_dense: np.ndarray, S_abs: np.ndarray, rhs_abs: np.ndarray) -> float | None:
    """The dense class's variance factor ``f`` that makes its pose estimate agree with an
    independent class in absolute units (Helmert's variance components on the poses):
    from one linearization, the dense-only step ``S_dense^-1 rhs_dense`` and the other class's
    ``S_abs^-1 rhs_abs`` (free poses only) differ by ``D``; ``f`` solves
    ``D^T (f S_dense^-1 + S_abs^-1)^-1 D = dim D``. This sees what residuals cannot: a bias
    or a correlated error that the dense class's own solution absorbs (its poses move with it
    and its residuals stay small). 0 when they agree within the other class's covariance
    alone; None when either system leaves a pose free."""
    m = len(rhs_dense)
    if m == 0:
        return None
    ev = np.linalg.eigvalsh(0.5 * (S_abs + S_abs.T))
    if ev[-1] <= 0 or ev[0] <= 1e-10 * ev[-1]:
        return None  # the other class leaves a pose (or a direction) free
    try:
        A = np.linalg.inv(S_dense + 1e-9 * np.trace(S_dense) / m * np.eye(m))
        B = np.linalg.inv(S_abs)
    except np.linalg.LinAlgError:
        return None
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
        return None
    D = A @ rhs_dense - B @ rhs_abs

    def chi2(f):
        return float(D @ np.linalg.solve(f * A + B, D))

    if chi2(0.0) <= m:
        return 0.0
    lo, hi = -12.0, 12.0  # log10 f
    if chi2(10.0**hi) > m:
        return 10.0**hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chi2(10.0**mid) > m else (lo, mid)
    return 10.0 ** (0.5 * (lo + hi))


def class_scales(reference: float | None, classes: list) -> list:
    """Weights [k] that multiply each class's information relative to the dense class, whose
    variance factor is ``reference``: ``reference / classes[k].sigma2`` for a
    :class:`ClassNoise`, ``reference * classes[k]`` for a class in absolute units (given as
    a number); 1 where either is unknown; clipped to :data:`SCALE_RANGE`."""
    out = []
    for c in classes:
        if reference is None or c is None:
            out.append(1.0)
            continue
        s = reference * (float(c) if isinstance(c, (int, float)) else 1.0 / c.sigma2)
        out.append(float(np.clip(s, *SCALE_RANGE)))
    return out
