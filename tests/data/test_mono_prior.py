"""The monocular-like priors of ``synth --depth mono``: each error of the realistic model
alone against its closed form, and the smooth model unchanged."""

from dataclasses import replace

import numpy as np
import pytest

from mcgs_warp.data.mono_prior import REALISTIC, SMOOTH, MonoErrors, depth_edges, mono_like_depth

# No blur, no field, no noise: each test switches on one effect.
NONE = MonoErrors(blur_px=1e-3, field_range=(1.0, 1.0), noise=0.0)


def scene():
    """[60,80]: a 2 m square on a 10 m wall, a floor strip from 20 to 100 m at the bottom."""
    d = np.full((60, 80), 10.0, np.float32)
    d[15:35, 20:40] = 2.0
    d[45:] = np.linspace(20.0, 100.0, 80)[None, :]
    return d


def test_per_object_scale_is_one_factor_per_region():
    d = scene()
    logs = []
    for seed in range(40):
        out = mono_like_depth(d, np.random.default_rng(seed), replace(NONE, object_sigma=0.08))
        ratio = out / d
        interior = [ratio[18:32, 23:37], ratio[2:12, 45:75]]  # the square, the wall (away from edges)
        for r in interior:
            assert r.std() < 1e-6 * r.mean()
        logs.append(np.log(interior[0].mean()))
    assert np.std(logs) == pytest.approx(0.08, rel=0.3)


def test_edge_bleeding_spreads_the_nearer_depth():
    """Within 3 px outside the square the wall takes the square's 2 m; further out it keeps 10 m."""
    d = scene()
    out = mono_like_depth(d, np.random.default_rng(0), replace(NONE, bleed_px=3))
    assert np.allclose(out[25, 40:42], 2.0) and np.allclose(out[25, 17:20], 2.0)
    assert np.allclose(out[25, 44:60], 10.0) and np.allclose(out[2:10, 50], 10.0)


def test_affine_error_in_inverse_depth():
    d = scene()
    out = mono_like_depth(d, np.random.default_rng(1), replace(NONE, affine_scale=(0.9, 1.1), affine_shift=0.02))
    A = np.stack([1.0 / d.ravel(), np.ones(d.size)], 1)
    (a, b), *_ = np.linalg.lstsq(A, 1.0 / out.ravel().astype(np.float64), rcond=None)
    assert 0.9 <= a <= 1.1 and abs(b) <= 0.02 and abs(a - 1) + abs(b) > 1e-3
    np.testing.assert_allclose(1.0 / out, a / d + b, rtol=1e-5)


def test_far_range_is_compressed_beyond_its_start():
    d = scene()
    out = mono_like_depth(d, np.random.default_rng(2), replace(NONE, far_start=15.0, far_scale=20.0))
    near = d <= 15.0
    np.testing.assert_allclose(out[near], d[near], rtol=1e-5)
    np.testing.assert_allclose(out[~near], 15.0 + 20.0 * np.log1p((d[~near] - 15.0) / 20.0), rtol=1e-5)
    assert out.max() == pytest.approx(15 + 20 * np.log(1 + 85 / 20), rel=1e-5)  # 100 m reads 48 m


def test_depth_edges_and_no_depth():
    d = scene()
    d[0, 0] = 0.0
    e = depth_edges(d, 0.1)
    assert e[25, 19] and e[25, 20] and not e[25, 30] and e[0, 1] and e[1, 0]
    out = mono_like_depth(d, np.random.default_rng(0), REALISTIC)
    assert out[0, 0] == 0.0 and (out[d > 0] > 0).all() and np.isfinite(out).all()


def test_realistic_errors_are_larger_than_the_smooth_field_alone():
    """On the built-in room: the realistic prior's log error is larger than the smooth one's,
    and no 3x3 smooth field explains it (the residual after dividing out the error's own
    smoothed version stays)."""
    import cv2

    from mcgs_warp.data.synthetic import SceneRenderer, build_scene, rig_trajectory, synthetic_rig

    rig = synthetic_rig(1)
    _, depth = SceneRenderer(build_scene(0), rig).render(rig_trajectory(3).poses[1])
    d = depth[0]
    err = {}
    for name, model in (("smooth", SMOOTH), ("realistic", REALISTIC)):
        out = mono_like_depth(d, np.random.default_rng(4), model)
        ok = (d > 0) & (out > 0)
        log = np.where(ok, np.log(np.where(ok, out, 1) / np.where(ok, d, 1)), 0).astype(np.float32)
        smooth = cv2.resize(cv2.resize(log, (6, 4), interpolation=cv2.INTER_AREA), log.shape[::-1], interpolation=cv2.INTER_LINEAR)
        err[name] = (np.abs(log[ok]).mean(), np.abs((log - smooth)[ok]).mean())
    assert err["realistic"][0] > 1.5 * err["smooth"][0], err
    assert err["realistic"][1] > 1.5 * err["smooth"][1], err
