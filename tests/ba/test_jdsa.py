"""JDSA: the scale grid fit, and its alternation with MCBA."""

import numpy as np

from mcgs_warp.ba.jdsa import bilinear_basis, mcba_with_jdsa, scale_field, solve_scales
from mcgs_warp.ba.mcba import MCBA, MCBAConfig
from problems import Problem


def test_bilinear_basis_interpolates_corners_and_sums_to_one():
    B = bilinear_basis(3, 4, 10, 13)
    np.testing.assert_allclose(B.sum(1), 1.0)
    s = np.arange(12.0).reshape(3, 4)
    f = scale_field(s, 10, 13)
    assert f[0, 0] == s[0, 0] and f[-1, -1] == s[-1, -1] and f[0, -1] == s[0, -1]
    assert np.isclose(f[0, 6], 1.5)  # halfway between columns 1 and 2 of the first row


def test_solve_scales_recovers_a_known_field():
    rng = np.random.default_rng(0)
    h, w = 30, 40
    depth = rng.uniform(1, 20, (h, w))
    s_true = rng.uniform(0.6, 1.5, (4, 6))
    prior = depth / scale_field(s_true, h, w)
    prior[rng.uniform(size=(h, w)) < 0.2] = 0  # holes in the prior
    np.testing.assert_allclose(solve_scales(prior, depth, (4, 6)), s_true, rtol=1e-4)  # tiny Tikhonov bias


def test_jdsa_with_mcba_recovers_the_prior_scale_field(synthetic_seq):
    """Monocular-like priors with a wrong, spatially varying scale: MCBA on exact
    correspondences (cross-view edges fix the metric scale) and JDSA together find
    the true depths and the scale grid that maps the priors onto them."""
    rng = np.random.default_rng(4)
    P = Problem(synthetic_seq, [0, 2, 4])
    buf = P.buf
    K, C = 3, len(buf.rig)
    s_true = rng.uniform(0.7, 1.4, (K, C, 4, 6))
    for k in range(K):
        for c in range(C):
            buf.depth_prior[k, c] = buf.depth_prior[k, c] / scale_field(s_true[k, c], buf.h, buf.w)
    prior_disp = np.where(buf.depth_prior[:K] > 0, 1.0 / np.maximum(buf.depth_prior[:K], 1e-6), 0)
    full = buf.disp.numpy()
    full[:K] = prior_disp  # start from the (wrongly scaled) priors
    buf.disp.assign(full)
    mcba = MCBA(buf, MCBAConfig(iterations=6, prior_weight=1e-3))
    mcba_with_jdsa(mcba, P.edges, P.targets, P.weights, rounds=4)
    assert np.median(P.depth_rel_errors()) < 2e-3
    # scales of grid cells that cover observed pixels
    err = np.abs(buf.scales[:K] / s_true - 1)
    assert np.median(err) < 0.02, np.median(err)


def test_scale_fit_ignores_depths_that_only_echo_the_prior():
    """JDSA weights each pixel by the inverse variance of its MCBA depth from the
    correspondences: where MCBA had nothing but the prior (information 0) its depth echoes
    the wrongly scaled prior and must not drag the grid; where it measured, the grid maps
    the prior onto the measured depth. Unweighted, the echo halves the correction."""
    from types import SimpleNamespace

    from mcgs_warp.ba.jdsa import depth_information, update_scales

    rng = np.random.default_rng(1)
    h, w = 30, 40
    true = rng.uniform(2, 8, (h, w))
    prior = true / 1.25  # the prior is 20 % short everywhere
    measured = np.zeros((h, w), bool)
    measured[:, ::2] = True  # every other column has correspondences
    mcba_depth = np.where(measured, true, prior)  # elsewhere MCBA depth just echoes the prior
    info = np.where(measured, 50.0, 0.0)

    class Buf:
        rig = [0]
        scales = np.ones((1, 1, 4, 6))
        depth_prior = prior[None, None].astype(np.float32)
        prior_conf = np.ones((1, 1, h, w), np.float32)
        disp = SimpleNamespace(numpy=lambda: (1.0 / mcba_depth)[None, None].astype(np.float32), shape=(1, 1, h, w))

    stats = SimpleNamespace(keyframes=[0], depth_info=info[None, None])
    update_scales(Buf, [0], depth_information(stats, Buf.disp.shape))
    np.testing.assert_allclose(Buf.scales[0, 0], 1.25, rtol=1e-3)
    Buf.scales = np.ones((1, 1, 4, 6))
    update_scales(Buf, [0])  # no information: the echoing half pulls the fit towards 1
    assert np.all(Buf.scales[0, 0] < 1.2)


def test_scale_fit_can_hold_the_mean_scale():
    """Without metric correspondences MCBA's depth carries an arbitrary overall scale
    (here 1.3 times the truth): a free fit passes it into the grids, ``hold_mean`` keeps
    their mean log scale and only aligns the views relative to each other."""
    from types import SimpleNamespace

    from mcgs_warp.ba.jdsa import update_scales

    rng = np.random.default_rng(2)
    h, w = 30, 40
    true = rng.uniform(2, 8, (2, 1, h, w))
    rel = np.array([1.25, 0.8])  # the true scale of each view's prior
    prior = (true / rel[:, None, None, None]).astype(np.float32)
    mcba_depth = 1.3 * true

    def buffer():
        return SimpleNamespace(
            rig=[0],
            scales=np.ones((2, 1, 4, 6)),
            depth_prior=prior,
            prior_conf=np.ones((2, 1, h, w), np.float32),
            disp=SimpleNamespace(numpy=lambda: (1.0 / mcba_depth).astype(np.float32), shape=(2, 1, h, w)),
        )

    free, held = buffer(), buffer()
    update_scales(free, [0, 1])
    update_scales(held, [0, 1], hold_mean=True)
    np.testing.assert_allclose(free.scales[:, 0], np.broadcast_to(1.3 * rel[:, None, None], (2, 4, 6)), rtol=1e-3)
    np.testing.assert_allclose(held.scales[:, 0], np.broadcast_to(rel[:, None, None], (2, 4, 6)), rtol=1e-3)  # mean log of (1.25, 0.8) is 0
