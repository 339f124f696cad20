"""Variance components (mcgs_warp/ba/variance.py): the robust scale and its redundancy
correction, the correlation of a residual field, and MCBA weighing a noisy or biased class
below a clean one; the keypoint odometry's covariance carries its measured variance."""

import numpy as np

from mcgs_warp.ba.keypoint_factors import KeypointFactors
from mcgs_warp.ba.mcba import MCBA, MCBAConfig
from mcgs_warp.ba.variance import correlation_factor, dense_noise, disagreement_factor, field_correlation, robust_variance
from mcgs_warp.frontend.keypoint_odometry import KeypointOdometry
from problems import Problem
from test_keypoint_factors import tracks


def test_robust_variance_corrects_for_what_the_solution_absorbed():
    """Pairs of samples around unknown means: residuals from the fitted means have half the
    variance; counting the means as unknowns recovers it. An outlier share does not move the
    MAD scale much."""
    rng = np.random.default_rng(0)
    x = rng.normal(rng.uniform(-5, 5, size=(3000, 1)), 0.3, size=(3000, 2))
    r = (x - x.mean(axis=1, keepdims=True)).ravel()
    naive, fixed = robust_variance(r), robust_variance(r, unknowns=3000)
    assert abs(naive.sigma2 / 0.09 - 0.5) < 0.05, naive
    assert abs(fixed.sigma2 / 0.09 - 1.0) < 0.1, fixed
    z = rng.normal(0, 0.3, 5000)
    z[:250] = 50.0  # 5 % gross outliers
    assert abs(robust_variance(z).sigma2 / 0.09 - 1.0) < 0.15
    assert robust_variance(np.ones(5)) is None


def _ar1_field(rng, rho, shape=(4, 60, 80)):
    """A separable AR(1) field [E,h,w,2] with lag-1 correlation ``rho`` along rows and columns."""
    f = rng.normal(size=shape + (2,))
    s = np.sqrt(1 - rho**2)
    for x in range(1, shape[2]):
        f[:, :, x] = rho * f[:, :, x - 1] + s * f[:, :, x]
    for y in range(1, shape[1]):
        f[:, y] = rho * f[:, y - 1] + s * f[:, y]
    return f


def test_field_correlation_measures_the_lag_one_correlation():
    rng = np.random.default_rng(1)
    valid = rng.uniform(size=(4, 60, 80)) > 0.2
    white = rng.normal(size=(4, 60, 80, 2))
    assert abs(field_correlation(white, valid)) < 0.03
    assert abs(field_correlation(_ar1_field(rng, 0.6), valid) - 0.6) < 0.05
    assert correlation_factor(0.0) == 1.0 and abs(correlation_factor(0.6) - 16.0) < 1e-9 and correlation_factor(-0.3) == 1.0


def test_median_abs_is_numpys_median_of_magnitudes():
    """From one copy in the input's dtype (global BA's millions of float32 residuals): the
    same float64 number as NumPy's median of magnitudes, for odd and even counts, skipping
    non-finite values, and the input untouched."""
    from mcgs_warp.ba.variance import median_abs

    rng = np.random.default_rng(4)
    for n in (1, 2, 7, 1000, 1001):
        z = rng.normal(size=n).astype(np.float32)
        keep = z.copy()
        assert median_abs(z) == (n, float(np.median(np.abs(z.astype(np.float64))))), n
        assert (z == keep).all()
    z = np.array([1.0, np.nan, -3.0, np.inf, 2.0, -0.5])
    assert median_abs(z) == (4, 1.5)
    assert median_abs(np.array([np.nan]))[0] == 0


def test_field_correlation_in_edge_chunks_is_the_pooled_correlation():
    """Summed a few edges at a time (bounded memory for a global solve's thousands of edges),
    the correlation is the one of all valid neighbour pairs pooled at once (each component
    about its own mean, outliers clipped at 3 robust sigmas), whatever the chunk size."""
    rng = np.random.default_rng(3)
    res = _ar1_field(rng, 0.4, (7, 20, 30)) * rng.uniform(0.5, 2.0, size=(7, 1, 1, 1))
    res[0, 3, 4] = 40.0  # an outlier, clipped
    valid = rng.uniform(size=(7, 20, 30)) > 0.3
    z = res[valid]
    sig = 1.4826 * np.median(np.abs(z))
    r = np.clip(res, -3 * sig, 3 * sig)
    xs, ys = [], []
    for a, b, va, vb in ((r[:, :, 1:], r[:, :, :-1], valid[:, :, 1:], valid[:, :, :-1]), (r[:, 1:], r[:, :-1], valid[:, 1:], valid[:, :-1])):
        m = va & vb
        xs.append(a[m] - a[m].mean(0))
        ys.append(b[m] - b[m].mean(0))
    x, y = np.concatenate(xs), np.concatenate(ys)
    want = (x * y).sum() / np.sqrt((x * x).sum() * (y * y).sum())
    for chunk in (1, 3, 64):
        assert abs(field_correlation(res, valid, chunk=chunk) - want) < 1e-12, chunk
    assert abs(field_correlation(res.astype(np.float32), valid) - want) < 1e-6  # MCBA's float32 field


def test_dense_noise_counts_each_views_depths_and_its_correlation():
    """Two edges leave each of two views: one depth per source pixel and view, so 4 components
    per pixel and view over 1 unknown; a correlated field costs information."""
    rng = np.random.default_rng(2)
    res = 0.1 * rng.normal(size=(4, 30, 40, 2))
    valid = np.ones((4, 30, 40), bool)
    n = dense_noise(res, valid, np.array([0, 0, 1, 1]))
    assert n.n == 4 * 30 * 40 * 2 and n.redundancy == n.n - 2 * 30 * 40
    assert abs(n.sigma2 / 0.01 - n.n / n.redundancy) < 0.1 and n.kappa < 1.2
    corr = dense_noise(0.1 * _ar1_field(rng, 0.7, (4, 30, 40)), valid, np.array([0, 0, 1, 1]))
    assert corr.kappa > 20, corr


def _solve(P, prob, variance_components=True):
    mcba = MCBA(P.buf, MCBAConfig(iterations=3, huber_delta=0.5, variance_components=variance_components))
    mcba.solve(P.edges, P.targets, P.weights, keyframes=[0, 1, 2, 3], keypoints=prob)  # the dense class's noise at a solution: the next solve's reference
    return mcba.solve(P.edges, P.targets, P.weights, keyframes=[0, 1, 2, 3], keypoints=prob)


def test_the_noise_is_measured_after_the_linearization_is_freed(synthetic_seq, monkeypatch):
    """The dense noise's residual field over every edge is a global solve's largest transient:
    the window's per-pixel couplings [E,h,w] are gone by then, and the noise is what it was."""
    import mcgs_warp.ba.mcba as mcba_module
    from problems import Problem

    P = Problem(synthetic_seq, [0, 2, 4, 6])
    seen = []
    noise = mcba_module._Window.noise

    def spy(self, keyframes):
        seen.append(self.Epix is None and self.blocks is None)
        return noise(self, keyframes)

    monkeypatch.setattr(mcba_module._Window, "noise", spy)
    st = MCBA(P.buf, MCBAConfig(iterations=2, huber_delta=0.5)).solve(P.edges, P.targets, P.weights, keyframes=[0, 1, 2, 3])
    assert seen == [True] and st.noise is not None and st.noise.n > 1000


def test_a_noisy_or_biased_class_loses_weight_against_a_clean_one(synthetic_seq):
    """Dense correspondences with 0.05 grid px of noise; keypoint tracks clean (0.2 px), noisy
    (2 px) or biased (one keyframe's observations 2 px off): the noisy tracks' weight falls by
    about the noise ratio squared (100), the biased ones' by more than 3x (a robust scale sees a
bias only where it leaves residuals: here in a quarter of the observations), and nominal weights
    (variance components off) give every class 1."""
    rng = np.random.default_rng(5)
    P = Problem(synthetic_seq, [0, 2, 4, 6], cross_view=False)
    P.targets = P.targets + rng.normal(0, 0.05, P.targets.shape).astype(np.float32)
    clean = tracks(synthetic_seq.rig, P.true_poses, 200, rng, noise_px=0.2)
    noisy = tracks(synthetic_seq.rig, P.true_poses, 200, rng, noise_px=2.0)
    biased = tracks(synthetic_seq.rig, P.true_poses, 200, rng, noise_px=0.2)
    biased.obs_uv[biased.obs_slot == 3] += 2.0
    w = {name: _solve(P, prob).scales[0] for name, prob in (("clean", clean), ("noisy", noisy), ("biased", biased))}
    assert 40 < w["clean"] / w["noisy"] < 250, w
    assert w["clean"] / w["biased"] > 3, w
    assert _solve(P, clean, variance_components=False).scales == [1.0]


def test_odometry_covariance_carries_the_measured_keypoint_noise(synthetic_seq):
    """The same window with 4x the keypoint noise: the step covariance grows about 16x (it was
    the same before: unit variance assumed)."""
    rig = synthetic_seq.rig
    poses = np.stack([synthetic_seq.groundtruth.poses[k] for k in range(0, 10, 2)])
    odo = KeypointOdometry(rig)
    covs = []
    for noise in (0.25, 1.0):
        prob = tracks(rig, poses, 300, np.random.default_rng(7), noise_px=noise)
        f = KeypointFactors(prob, rig, 8, 10.0, 1e-3)  # a wide Huber threshold: least squares
        covs.append(np.trace(odo.step_covariance(f, poses)))
    assert 10 < covs[1] / covs[0] < 25, covs
    # a measured step that holds the frame before the newest (a two-view step, already in the
    # tracks' units) takes part in the newest step's covariance: it shrinks
    from mcgs_warp.ba.pose_factors import RelativePoseFactors

    held = RelativePoseFactors([(2, 3)], [np.linalg.inv(poses[2]) @ poses[3]], [1e8 * np.eye(6)])
    assert np.trace(odo.step_covariance(f, poses, held)) < 0.9 * covs[1]


def test_disagreement_factor_recovers_the_dense_variance_and_sees_a_bias():
    """Two estimates of 24 pose parameters: the 'dense' one with covariance f * S_dense^-1
    (f = 25: its nominal weights 25x too confident), the other with its true covariance. One
    realization's disagreement gives f within 2x (the median of 20); a truly precise dense class
    comes out far below it (what the other class's own noise leaves unresolved); a bias
    the dense residuals cannot show makes f large."""
    rng = np.random.default_rng(3)
    m = 24
    Q = np.linalg.qr(rng.normal(size=(m, m)))[0]
    S_dense = Q @ np.diag(rng.uniform(50, 500, m)) @ Q.T
    S_abs = np.diag(rng.uniform(5, 20, m))
    x = rng.normal(size=m)

    def rhs(cov, bias=0.0):
        est = x + np.linalg.cholesky(cov) @ rng.normal(size=m) + bias
        return est  # S @ est is the rhs whose step is est

    A, B = np.linalg.inv(S_dense), np.linalg.inv(S_abs)
    f = [disagreement_factor(S_dense, S_dense @ rhs(25 * A), S_abs, S_abs @ rhs(B)) for _ in range(20)]
    assert 12 < np.median(f) < 50, f
    precise = np.median([disagreement_factor(S_dense, S_dense @ rhs(1e-4 * A), S_abs, S_abs @ rhs(B)) for _ in range(20)])
    assert precise < 0.2 * np.median(f), precise
    biased = disagreement_factor(S_dense, S_dense @ rhs(1e-4 * A, bias=0.5), S_abs, S_abs @ rhs(B))
    assert biased > 10 * precise, (biased, precise)
    assert disagreement_factor(S_dense, S_dense @ x, np.zeros((m, m)), np.zeros(m)) is None  # the other class leaves poses free


def test_mcba_weighs_biased_dense_flow_below_an_odometry_that_disagrees(synthetic_seq):
    """Dense flow biased by 0.2 grid px on the last keyframe's edges (a bias its own residuals
    hide: the pose absorbs it) against relative-pose factors at the true motion with their
    true covariance (1 mm, 0.01 deg): the dense class's measured variance grows, the odometry's
    weight in the next solve with it, and that solve lands nearer the truth than with the
    nominal weights."""
    from mcgs_warp.ba.pose_factors import RelativePoseFactors
    from mcgs_warp.geometry import invert

    def run(bias, vc):
        rng = np.random.default_rng(6)
        P = Problem(synthetic_seq, [0, 2, 4, 6], cross_view=False)
        P.targets = P.targets + rng.normal(0, 0.02, P.targets.shape).astype(np.float32)
        P.targets[P.edges[:, 2] == 3] += np.float32(bias)
        T = P.true_poses
        info = np.diag([1e6] * 3 + [1.0 / np.radians(0.01) ** 2] * 3)
        odo = RelativePoseFactors([(0, 1), (1, 2), (2, 3)], [invert(T[a]) @ T[b] for a, b in [(0, 1), (1, 2), (2, 3)]], [info] * 3)
        mcba = MCBA(P.buf, MCBAConfig(iterations=4, huber_delta=0.5, variance_components=vc))
        for _ in range(3):
            P.perturb(rng, trans=0.03, rot_deg=0.5)
            st = mcba.solve(P.edges, P.targets, P.weights, keyframes=[0, 1, 2, 3], factors=[odo])
        return mcba, st, P.pose_errors()[1:, 0].max()

    clean, st_clean, _ = run(0.0, True)
    biased, st_biased, err = run(0.2, True)
    _, _, err_nominal = run(0.2, False)
    assert biased.dense_variance() > 10 * clean.dense_variance(), (biased.disagreement, clean.disagreement)
    assert st_biased.scales[0] > 10 * st_clean.scales[0]
    assert err < 0.5 * err_nominal, (err, err_nominal)
