"""Sensor-depth alignment in MCBA: the residual's Jacobian against finite differences, and
poses recovered from depth alone (the photometric correspondences carry no weight: a
textureless scene with good depth)."""

import numpy as np

from mcgs_warp.ba.depth_factors import DepthAlignmentFactors
from mcgs_warp.ba.mcba import MCBA, MCBAConfig
from mcgs_warp.geometry import se3_exp
from problems import Problem, perturbed_pair


def factors_args(P, weight=30.0, delta=1.0):
    """Rays, cameras, extrinsics, weight and threshold of ``P``'s depth factors."""
    buf = P.buf
    return buf.rays.numpy().astype(np.float64), [c.warp_camera() for c in buf.reduced], np.stack([c.T_b_c for c in buf.rig.cameras]), weight, delta


def factors(P, weight=30.0, delta=1.0):
    depth = P.buf.depth_prior.numpy()[: len(P.true_poses)]
    edges = P.edges[P.edges[:, 0] != P.edges[:, 2]]
    return DepthAlignmentFactors(edges, depth, *factors_args(P, weight, delta))


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


def test_depth_alignment_memory_is_bounded_by_the_chunk(synthetic_seq, monkeypatch):
    """Global BA gives these factors every edge of the run (millions of samples): the Gauss-Newton
    terms are built a chunk of samples at a time, so their temporaries do not grow with the
    sample count (they were [n,12,12] float64 at once: 3.6 GB on the 160-frame room loop)."""
    import tracemalloc

    from mcgs_warp.ba import depth_factors

    monkeypatch.setattr(depth_factors, "CHUNK", 2048, raising=False)
    P = Problem(synthetic_seq, [0, 2, 4])
    base = factors(P)
    poses = P.true_poses @ np.stack([se3_exp(np.array([0.01, -0.02, 0.01, 0.01, 0.0, -0.01]) * k) for k in range(3)])
    edges = P.edges[P.edges[:, 0] != P.edges[:, 2]]
    peaks = {}
    for copies in (2, 16):  # the same edges repeated: more samples, the same keyframes
        f = DepthAlignmentFactors(np.tile(edges, (copies, 1)), base.depth, *factors_args(P))
        assert len(f) == copies * len(base) > 4 * 2048
        tracemalloc.start()
        f.reduced_terms(poses, 0.0)
        peaks[copies] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peaks[16] < 1.5 * peaks[2], f"peak {peaks[2] / 1e6:.1f} MB -> {peaks[16] / 1e6:.1f} MB with 8x the samples"


def test_depth_alignment_chunks_add_up_to_the_whole(synthetic_seq, monkeypatch):
    """Chunk borders fall inside edges: the terms are the same as in one pass, up to rounding."""
    from mcgs_warp.ba import depth_factors

    P = Problem(synthetic_seq, [0, 2, 4])
    f = factors(P)
    poses = P.true_poses @ np.stack([se3_exp(np.array([0.01, -0.02, 0.01, 0.01, 0.0, -0.01]) * k) for k in range(3)])
    whole = f.reduced_terms(poses, 0.0), f.residuals(poses), [f.agreement(poses, s) for s in range(3)]
    monkeypatch.setattr(depth_factors, "CHUNK", 997, raising=False)
    assert len(f) > 3 * 997
    (S, rhs), (r, valid), agree = f.reduced_terms(poses, 0.0), f.residuals(poses), [f.agreement(poses, s) for s in range(3)]
    np.testing.assert_allclose(S, whole[0][0], rtol=1e-12, atol=1e-12 * np.abs(S).max())
    np.testing.assert_allclose(rhs, whole[0][1], rtol=1e-12, atol=1e-12 * np.abs(rhs).max())
    np.testing.assert_array_equal(r, whole[1][0])
    np.testing.assert_array_equal(valid, whole[1][1])
    for a, b in zip(agree, whole[2]):
        np.testing.assert_array_equal(a, b)
