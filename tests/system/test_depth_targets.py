"""The mapper's depth targets (:class:`~mcgs_warp.system.depth_targets.DepthTargets`) on a
hand-built keyframe buffer, no SLAM run: the measured weights, which grid pixels count as
measured, the guided upsampling's reach, the JDSA-scaled prior where it agrees, and the sweep
depth (its sources, the fill, the cache)."""

from types import SimpleNamespace

import numpy as np

from mcgs_warp.ba.graph import FactorGraph
from mcgs_warp.buffer import KeyframeBuffer
from mcgs_warp.frontend.depth import NoDepth, SensorDepth
from mcgs_warp.rig import CameraSpec, Rig
from mcgs_warp.system.depth_targets import DepthTargets

# camera a: 16x12 px, a 4x3 grid at stride 4; camera b: 8x8 px, a 2x2 grid (the buffer's grid is 4x3)
RIG = Rig([CameraSpec("a", "pinhole", 16, 12, (10.0, 10.0, 7.5, 5.5)), CameraSpec("b", "pinhole", 8, 8, (6.0, 6.0, 3.5, 3.5))])
GRID = (2, 3, 4)  # [C,h,w]


def _images(grey):
    return [np.full((c.height, c.width, 3), grey, np.float32) for c in RIG.cameras]


def _buffer(xs, prior_conf=None):
    """Keyframes at rig positions ``xs`` (m, along x): grid depth 2 m in camera a and 4 m in
    camera b; keyframe k's images a flat grey 0.1 (k + 1)."""
    buf = KeyframeBuffer(RIG, stride=4, device="cpu")
    disp = np.zeros(GRID, np.float32)
    disp[0], disp[1, :2, :2] = 0.5, 0.25
    for k, x in enumerate(xs):
        T = np.eye(4)
        T[0, 3] = x
        buf.add(k, 0.1 * k, _images(0.1 * (k + 1)), T, disp, depth_prior=None if prior_conf is None else np.zeros(GRID), prior_conf=prior_conf)
    return buf


def _graph(buf):
    """Edges of keyframe 1 with confidences 0.75 (camera a to keyframe 0, every pixel), 0.25
    (camera a to camera b, the left two grid columns), 1.0 at camera b's first grid pixel and
    0.5 at its others (to keyframe 0); and one edge leaving keyframe 0 that must not count."""
    graph = FactorGraph(buf)
    w = np.zeros((4,) + GRID[1:], np.float32)
    w[0] = 0.75
    w[1, :, :2] = 0.25
    w[2, :2, :2] = 0.5
    w[2, 0, 0] = 1.0
    w[3] = 1.0
    graph.add(np.array([(1, 0, 0, 0), (1, 0, 1, 1), (1, 1, 0, 1), (0, 0, 1, 0)]), np.zeros(w.shape + (2,), np.float32), w)
    return graph


class Stereo:
    """The parts of :class:`RigStereo` a sweep reads: no rig pairs; ``temporal_depth``
    answers 3 m everywhere at half resolution and records what it was given."""

    pairs: list = []
    cfg = SimpleNamespace(scale=2, temporal_sources=2, temporal_baseline=0.5)

    def __init__(self):
        self.calls = []

    def temporal_depth(self, index, images, views):
        self.calls.append((index, views))
        return [np.full((c.height // 2, c.width // 2), 3.0, np.float32) for c in RIG.cameras]


def _targets(buf, prior=None, metric_scale=False, stereo=None):
    return DepthTargets(buf, RIG, prior or NoDepth(), stereo or Stereo(), _graph(buf), exact=False, metric_scale=metric_scale, window=8)


def _frame(k, depths=None):
    return SimpleNamespace(index=k, images=_images(0.1 * (k + 1)), depths=depths)


def _pixels(c):
    spec = RIG.cameras[c]
    return np.mgrid[0 : spec.height, 0 : spec.width]  # y, x


def test_measured_weight_and_constrained_pixels():
    """Keyframe 1's measured weight sums the confidences of the edges leaving it, per camera;
    a grid pixel counts as measured from a weight of 1 (0.75 + 0.25 is, 0.75 alone is not),
    or with a metric prior whose confidence exceeds 0.5 (0.5 does not)."""
    conf = np.full(GRID, 0.5, np.float32)
    conf[0, 2, 3] = 0.9
    targets = _targets(_buffer([0.0, 1.0], prior_conf=conf))
    weight = targets.measured_weight([1, 1])
    assert list(weight) == [1]
    expected = np.zeros(GRID, np.float32)
    expected[0], expected[0, :, :2] = 0.75, 1.0
    expected[1, :2, :2], expected[1, 0, 0] = 0.5, 1.0
    np.testing.assert_array_equal(weight[1], expected)
    np.testing.assert_array_equal(targets.constrained(1, weight[1]), expected >= 1.0)
    metric = _targets(targets.buf, prior=SensorDepth(exact=False))
    np.testing.assert_array_equal(metric.constrained(1, weight[1]), (expected >= 1.0) | (conf > 0.5))
    assert metric.constrained(1, weight[1]).sum() == 3 * 2 + 1 + 1


def test_targets_upsample_the_measured_grid_depth_and_nothing_else():
    """Without a prior or a sweep, a camera's target is its measured grid depth, upsampled:
    a full-resolution pixel takes the depth of the 2x2 grid samples around it that are
    measured (grid column u' sits at x = 4 u' + 2), 0 where none is."""
    targets = _targets(_buffer([0.0, 1.0]))
    a, b = targets.compute(_frame(1), 1, lost=[], kept=[])
    y, x = _pixels(0)
    np.testing.assert_array_equal(a, np.where(x < 10, 2.0, 0.0))  # grid columns 0 and 1 measured
    y, x = _pixels(1)
    np.testing.assert_array_equal(b, np.where((x < 6) & (y < 6), 4.0, 0.0))  # grid pixel (0, 0) alone
    assert targets.sweeps == {}
    exact = DepthTargets(targets.buf, RIG, SensorDepth(), Stereo(), targets.graph, exact=True, metric_scale=True, window=8)
    depths = [np.ones((12, 16), np.float32), np.ones((8, 8), np.float32)]
    assert all(t is d for t, d in zip(exact.compute(_frame(1, depths), 1, [], []), depths))


def test_the_jdsa_scaled_prior_replaces_the_depth_it_agrees_with():
    """A metric prior, scaled by keyframe 1's JDSA grids (1.1 everywhere), takes the target
    where it lies within 10 % of the upsampled depth: camera a's upper half (1.9 m -> 2.09 m
    against 2 m) and camera b (3.8 m -> 4.18 m against 4 m), not camera a's lower half (1.5 m
    -> 1.65 m). Its confidence 0.9 at camera a's grid pixel (row 2, column 3) measures it:
    the lower right corner gets a depth too; the upper right none (nor the prior there)."""
    conf = np.full(GRID, 0.5, np.float32)
    conf[0, 2, 3] = 0.9
    buf = _buffer([0.0, 1.0], prior_conf=conf)
    buf.scales[1].assign(np.full((2,) + buf.scale_grid, 1.1))
    prior = [np.where(np.arange(12)[:, None] < 6, np.float32(1.9), np.float32(1.5)) * np.ones((12, 16), np.float32), np.full((8, 8), 3.8, np.float32)]
    a, b = _targets(buf, prior=SensorDepth(exact=False)).compute(_frame(1, prior), 1, [], [])
    y, x = _pixels(0)
    measured = (x < 10) | (y >= 6)
    upper = np.float32(1.9) * np.float32(1.1)
    np.testing.assert_allclose(a, np.where(measured, np.where(y < 6, upper, 2.0), 0.0), rtol=1e-6)
    y, x = _pixels(1)
    np.testing.assert_allclose(b, np.where((x < 6) & (y < 6), np.float32(3.8) * np.float32(1.1), 0.0), rtol=1e-6)


def test_the_sweep_fills_what_nothing_else_measured_from_verified_keyframes():
    """Sweep sources are the nearest earlier keyframes at least ``temporal_baseline`` away
    whose poses tracking measured (not lost, not kept), else later ones, at most
    ``temporal_sources``; each view goes with its pose relative to the keyframe's camera.
    The sweep is kept in float16 once computed from a source; a kept keyframe, or a run
    without metric scale, has none."""
    buf = _buffer([0.0, 0.3, 1.0, 2.0])
    stereo = Stereo()
    targets = _targets(buf, metric_scale=True, stereo=stereo)
    swept = targets.sweep(3, _frame(3), lost=[2], kept=[])
    (index, views), = stereo.calls
    assert index == 3 and [len(v) for v in views] == [2, 2]
    for c in range(2):
        for (image, T), j, dx in zip(views[c], (1, 0), (1.7, 2.0)):  # keyframe 2 is lost
            np.testing.assert_array_equal(image, np.full((RIG.cameras[c].height, RIG.cameras[c].width, 3), np.float32(0.1 * (j + 1))))
            np.testing.assert_allclose(T[:3, 3], [dx, 0.0, 0.0], atol=1e-6)
    assert all(d.dtype == np.float16 for d in swept) and targets.sweeps[3] is swept
    assert targets.sweep(3, _frame(3), [2], []) is swept and len(stereo.calls) == 1  # once
    targets.sweep(1, _frame(1), [], [])  # keyframe 0 only 0.3 m away: the later keyframes 2 and 3
    np.testing.assert_allclose([T[0, 3] for _, T in stereo.calls[-1][1][0]], [-0.7, -1.7], atol=1e-6)
    assert targets.sweep(2, _frame(2), [], kept=[2]) is None and 2 not in targets.sweeps  # kept: no source, no rig pair
    assert _targets(buf, metric_scale=False, stereo=stereo).sweep(3, _frame(3), [], []) is None
    a, b = targets.compute(_frame(3), 3, [2], [])  # keyframe 3 has no edges: the sweep (3 m) everywhere
    np.testing.assert_array_equal(a, 3.0)
    np.testing.assert_array_equal(b, 3.0)
    a, b = targets.compute(_frame(1), 1, [], [])  # keyframe 1: its measured depth, the sweep beside it
    y, x = _pixels(0)
    np.testing.assert_array_equal(a, np.where(x < 10, 2.0, 3.0))
