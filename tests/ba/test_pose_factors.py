"""Relative-pose factors (the keypoint odometry's motion between keyframes) in MCBA: the
SE(3) logarithm and its Jacobian, the factors' Jacobians against finite differences, and an
MCBA solve whose dense correspondences carry no weight recovering the poses from the
measured motions alone."""

import numpy as np

from mcgs_warp.ba.mcba import MCBA, MCBAConfig
from mcgs_warp.ba.pose_factors import RelativePoseFactors, se3_right_jacobian_inv
from mcgs_warp.geometry import invert, se3_exp, se3_log
from problems import Problem, perturbed_pair


def test_se3_log_inverts_exp_and_right_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    for scale in (1e-7, 0.3, 2.5):  # near identity, moderate, large rotation
        xi = rng.normal(size=6) * scale
        xi[3:] *= min(1.0, 3.0 / max(np.linalg.norm(xi[3:]), 1e-12))  # |phi| < pi
        np.testing.assert_allclose(se3_log(se3_exp(xi)), xi, atol=1e-9)
        J = se3_right_jacobian_inv(xi)
        eps = 1e-6
        num = np.stack([(se3_log(se3_exp(xi) @ se3_exp(eps * e)) - se3_log(se3_exp(xi) @ se3_exp(-eps * e))) / (2 * eps) for e in np.eye(6)], 1)
        np.testing.assert_allclose(J, num, atol=1e-6)


def _chain(rng, n=4):
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ se3_exp(np.concatenate([rng.normal(0, 0.5, 3), rng.normal(0, 0.1, 3)])))
    return np.stack(poses)


def test_relative_pose_factor_jacobians_match_finite_differences():
    rng = np.random.default_rng(1)
    truth = _chain(rng)
    pairs = [(0, 1), (1, 2), (2, 3), (0, 3)]
    motions = [invert(truth[a]) @ truth[b] @ se3_exp(rng.normal(0, 0.05, 6)) for a, b in pairs]  # residuals not zero: Jr^-1 matters
    info = []
    for _ in pairs:
        A = rng.normal(size=(6, 6))
        info.append(A @ A.T + np.eye(6))
    f = RelativePoseFactors(pairs, motions, info)
    poses = truth @ np.stack([se3_exp(rng.normal(0, 0.03, 6)) for _ in truth])
    r, Ja, Jb = f.jacobians(poses)
    eps = 1e-6
    for p, (a, b) in enumerate(pairs):
        for s, J in ((a, Ja[p]), (b, Jb[p])):
            num = np.zeros((6, 6))
            for k in range(6):
                Pp, Pm = perturbed_pair(poses, s, k, eps)
                num[:, k] = (f.residuals(Pp)[p] - f.residuals(Pm)[p]) / (2 * eps)
            np.testing.assert_allclose(J, num, atol=1e-6)
    S, rhs = f.reduced_terms(poses, 0.0)  # rhs = -grad of the cost
    for s in range(len(poses)):
        for k in range(6):
            Pp, Pm = perturbed_pair(poses, s, k, eps)
            np.testing.assert_allclose(-rhs[6 * s + k], (f.cost(Pp) - f.cost(Pm)) / (2 * eps), rtol=1e-5, atol=1e-7)


def test_mcba_recovers_poses_from_relative_motions_alone(synthetic_seq):
    rng = np.random.default_rng(7)
    P = Problem(synthetic_seq, [0, 2, 4, 6])
    truth = P.true_poses.copy()
    P.perturb(rng, trans=0.05, rot_deg=2.0, depth_noise=0.0)
    before = P.pose_errors()[1:].max(0)
    pairs = [(0, 1), (1, 2), (2, 3)]
    info = np.diag([1e4] * 3 + [1e5] * 3)  # 1 cm, 3 mrad
    f = RelativePoseFactors(pairs, [invert(truth[a]) @ truth[b] for a, b in pairs], [info] * 3)
    stats = MCBA(P.buf, MCBAConfig(iterations=10)).solve(P.edges, P.targets, np.zeros_like(P.weights), keyframes=[0, 1, 2, 3], factors=[f])
    err = P.pose_errors()[1:].max(0)
    assert stats.accepted > 0
    assert before[0] > 0.03 and err[0] < 1e-4 and err[1] < 1e-3, (before, err)


def test_a_wrong_odometry_motion_does_not_drag_the_window(synthetic_seq):
    """Exact dense matches and three odometry motions, one of them 30 cm off (a bad PnP), each
    as confident as a good one (1 cm), against dense matches at their nominal weight: least
    squares (an infinite Huber threshold) moves the window by the whole 30 cm, the robust
    cost by a sixth of it (its pull is bounded at 3 sigma)."""
    from mcgs_warp.geometry import se3_exp

    def solve(huber):
        rng = np.random.default_rng(8)
        P = Problem(synthetic_seq, [0, 2, 4, 6], cross_view=False)
        truth = P.true_poses.copy()
        P.perturb(rng, trans=0.02, rot_deg=0.5, depth_noise=0.0)
        pairs = [(0, 1), (1, 2), (2, 3)]
        motions = [invert(truth[a]) @ truth[b] for a, b in pairs]
        motions[1] = motions[1] @ se3_exp(np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0]))
        f = RelativePoseFactors(pairs, motions, [np.diag([1e4] * 3 + [1e5] * 3)] * 3, huber=huber)
        MCBA(P.buf, MCBAConfig(iterations=10, variance_components=False)).solve(P.edges, P.targets, P.weights, keyframes=[0, 1, 2, 3], factors=[f])
        return P.pose_errors()[1:, 0].max()

    robust, plain = solve(3.0), solve(np.inf)
    assert plain > 0.25 and plain > 5 * robust, (robust, plain)
