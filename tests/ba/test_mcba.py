"""MCBA recovers known poses and depths from perturbed starts (exact correspondences)."""

import numpy as np

from mcgs_warp.ba.mcba import MCBA, MCBAConfig
from mcgs_warp.data.sequence import CameraSubset
from problems import Problem


def test_three_camera_rig_converges_to_ground_truth(synthetic_seq):
    P = Problem(synthetic_seq, [0, 2, 4, 6])
    P.perturb(np.random.default_rng(0), trans=0.05, rot_deg=2.0, depth_noise=0.1)
    before = P.pose_errors().max(0)
    assert before[0] > 0.04 and before[1] > 1.9
    stats = MCBA(P.buf, MCBAConfig(iterations=6)).solve(P.edges, P.targets, P.weights)
    err = P.pose_errors()
    # README ("Tracking"): below 1e-6 m in a few iterations (float32 kernels: ~1e-7 m here).
    assert err[:, 0].max() < 1e-6 and err[:, 1].max() < 1e-4, err
    assert np.median(P.depth_rel_errors()) < 1e-5
    assert stats.cost[-1] < 1e-6 * stats.cost[0]
    assert np.all(np.diff(stats.cost) <= 0)  # LM only accepts descending steps


def test_single_camera_converges_with_a_depth_prior(synthetic_seq):
    """One camera cannot see metric scale; a (sensor) depth prior supplies it."""
    P = Problem(CameraSubset(synthetic_seq, [0]), [0, 2, 4, 6], cross_view=False)
    assert set(P.edges[:, 1]) == {0}
    P.perturb(np.random.default_rng(1), trans=0.05, rot_deg=2.0, depth_noise=0.1)
    MCBA(P.buf, MCBAConfig(iterations=10, prior_weight=1.0)).solve(P.edges, P.targets, P.weights)
    err = P.pose_errors()
    assert err[:, 0].max() < 1e-3 and err[:, 1].max() < 0.01, err
    assert np.median(P.depth_rel_errors()) < 1e-3


def test_cross_view_edges_alone_fix_metric_scale(synthetic_seq):
    """Depths all 40% too far, one keyframe, only cross-view edges: the known baselines
    between the cameras pull the depths back to metric scale."""
    P = Problem(synthetic_seq, [3], temporal=False)
    assert len(P.edges) > 0 and np.all(P.edges[:, 0] == P.edges[:, 2])
    P.perturb(np.random.default_rng(2), trans=0.0, rot_deg=0.0, depth_noise=0.02, depth_scale=1.4)
    assert np.median(P.depth_rel_errors()) > 0.3
    MCBA(P.buf, MCBAConfig(iterations=15)).solve(P.edges, P.targets, P.weights, fixed=[0])
    rel = P.depth_rel_errors()
    assert np.median(rel) < 1e-3, np.median(rel)


def test_no_edges_changes_nothing(synthetic_seq):
    P = Problem(synthetic_seq, [0, 2])
    before = P.buf.get_poses()
    stats = MCBA(P.buf).solve(P.edges[:0], P.targets[:0], P.weights[:0], keyframes=[0, 1])
    assert stats.accepted == 0 and np.array_equal(P.buf.get_poses(), before)


def test_bootstrap_from_zero_baseline_keeps_depths(synthetic_seq):
    """The first solve of a sequence: the second keyframe starts at the first one's pose
    (no baseline yet), every depth at one constant, no prior. Depths the start barely
    observes must not run off towards the camera (they did, to ~1 mm, under multiplicative
    damping alone); the solve finds the motion and the depths."""
    P = Problem(synthetic_seq, [0, 2])
    T = P.true_poses.copy()
    T[1] = T[0]
    P.buf.set_poses(T)
    start = np.median(1.0 / P.true_disp[P.true_disp > 0])
    disp = P.buf.disp.numpy()
    disp[:2] = np.where(P.true_disp > 0, 1.0 / start, 0.0)
    P.buf.disp.assign(disp)
    assert P.pose_errors()[1, 0] > 0.25  # the true baseline (0.3 m)
    MCBA(P.buf, MCBAConfig(iterations=15)).solve(P.edges, P.targets, P.weights)
    d = P.buf.disp.numpy()[:2]
    assert d.max() < 1.0 / 0.5, d.max()  # nothing nearer than 0.5 m (the scene: >= 0.6 m)
    assert P.pose_errors()[1, 0] < 0.01, P.pose_errors()
    assert np.median(P.depth_rel_errors()) < 0.01, np.median(P.depth_rel_errors())


def test_huber_weighting_shrugs_off_outlier_correspondences(synthetic_seq):
    """A tenth of the correspondences moved 2-6 grid px (a bad match each), at full weight:
    with MCBA's Huber threshold (0.1 grid px) the solve still lands on the true poses; with
    the threshold so large that the cost is plain least squares, the outliers pull it off."""
    rng = np.random.default_rng(3)

    def solve(huber):
        P = Problem(synthetic_seq, [0, 2, 4, 6])
        targets = P.targets.copy()
        bad = (rng.random(P.weights.shape) < 0.1) & (P.weights > 0)
        angle = rng.uniform(0, 2 * np.pi, bad.sum())
        targets[bad] += rng.uniform(2, 6, bad.sum())[:, None] * np.stack([np.cos(angle), np.sin(angle)], 1)
        P.perturb(np.random.default_rng(0), trans=0.05, rot_deg=2.0, depth_noise=0.1)
        MCBA(P.buf, MCBAConfig(iterations=10, huber_delta=huber)).solve(P.edges, targets, P.weights)
        return P.pose_errors().max(0)

    robust, plain = solve(0.1), solve(1e6)
    # measured: 0.6 mm / 0.003 deg robust, 8.6 mm / 0.074 deg plain
    assert robust[0] < 0.0015 and robust[1] < 0.01, robust
    assert plain[0] > 5 * robust[0] and plain[1] > 5 * robust[1], (plain, robust)


def test_an_ill_conditioned_system_is_a_rejected_step_not_a_warning(synthetic_seq, monkeypatch):
    """SciPy's LinAlgWarning (an ill-conditioned reduced system) never reaches the console:
    MCBA takes it as no step and damps more, so the state stays where it was."""
    import warnings

    import scipy.linalg

    P = Problem(synthetic_seq, [0, 2])
    P.perturb(np.random.default_rng(3), trans=0.05, rot_deg=1.0)
    before = P.buf.get_poses().copy()

    def ill(*args, **kwargs):
        warnings.warn("Ill-conditioned matrix (rcond=1e-20): result may not be accurate.", scipy.linalg.LinAlgWarning)
        return np.ones(len(args[1]))

    monkeypatch.setattr(scipy.linalg, "solve", ill)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning that escapes fails the test
        stats = MCBA(P.buf, MCBAConfig(iterations=2)).solve(P.edges, P.targets, P.weights)
    assert stats.accepted == 0 and stats.rejected > 0
    np.testing.assert_array_equal(P.buf.get_poses(), before)
