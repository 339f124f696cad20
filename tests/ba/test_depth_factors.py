"""Sensor-depth alignment in MCBA: the residual's Jacobian against finite differences, and
poses recovered from depth alone (the photometric correspondences carry no weight: a
textureless scene with good depth)."""

import numpy as np

from mcgs_warp.ba.depth_factors import DepthAlignmentFactors
from mcgs_warp.ba.mcba import MCBA, MCBAConfig
from mcgs_warp.geometry import se3_exp
from problems import Problem, perturbed_pair


def factors(P, weight=30.0, delta=1.0):
    buf = P.buf
    n = len(P.true_poses)
    depth = buf.depth_prior.numpy()[:n]
    edges = P.edges[P.edges[:, 0] != P.edges[:, 2]]
    return DepthAlignmentFactors(edges, depth, buf.rays.numpy().astype(np.float64), [c.warp_camera() for c in buf.reduced], np.stack([c.T_b_c for c in buf.rig.cameras]), weight, delta)


def test_depth_alignment_jacobian_matches_finite_differences(synthetic_seq):
    P = Problem(synthetic_seq, [0, 2, 4])
    f = factors(P)
    poses = P.true_poses @ np.stack([se3_exp(np.array([0.01, -0.02, 0.01, 0.01, 0.0, -0.01]) * k) for k in range(3)])
    S, rhs = f.reduced_terms(poses, 0.0)
    r0, valid = f.residuals(poses)
    assert valid.sum() > 500
    # rhs = -J^T W r with W = weight inside the Huber threshold: compare J^T r by finite differences of the cost
    eps = 1e-6
    for s in (1, 2):
        for k in range(6):
            Pp, Pm = perturbed_pair(poses, s, k, eps)
            num = (f.cost(Pp) - f.cost(Pm)) / (2 * eps)
            np.testing.assert_allclose(-rhs[6 * s + k], num, rtol=2e-3, atol=1e-6)


def test_mcba_tracks_from_sensor_depth_alone(synthetic_seq):
    rng = np.random.default_rng(5)
    P = Problem(synthetic_seq, [0, 2, 4])
    P.perturb(rng, trans=0.04, rot_deg=1.5, depth_noise=0.0)
    before = P.pose_errors()[1:].max(0)
    f = factors(P, delta=0.1)
    stats = MCBA(P.buf, MCBAConfig(iterations=10)).solve(P.edges, P.targets, np.zeros_like(P.weights), factors=[f])
    err = P.pose_errors()[1:].max(0)
    assert stats.accepted > 0
    # 4 cm / 1.5 deg down to ~6 mm / 0.1 deg: the target depth is looked up on the 8 px grid
    # (bilinear in inverse depth, exact for planes seen by a pinhole, not for the fisheye)
    assert before[0] > 0.03 and err[0] < 0.01 and err[1] < 0.15, (before, err)
