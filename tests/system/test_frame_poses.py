"""The frames between keyframes: placed by the keypoint odometry (moved by the keyframes'
correction) where it tracked the span, else interpolated in time."""

from types import SimpleNamespace

import numpy as np

from mcgs_warp.geometry import se3_exp
from mcgs_warp.system.tracker import Tracker


def _curve(n):
    """A car turning and braking: rig poses [n,4,4] at 10 Hz."""
    poses, T = [], np.eye(4)
    for i in range(n):
        poses.append(T.copy())
        T = T @ se3_exp([0.0, 0.0, 1.5 - 0.12 * i, 0.0, 0.12, 0.0])  # forward, slowing, yawing
    return np.stack(poses)


def _slam(truth, kf, filler):
    """The parts of a tracker that :meth:`Tracker.trajectory` reads: keyframe poses, times and
    frames, frame times, image motions, and the filler's poses."""
    stamps = 0.1 * np.arange(len(truth))
    buf = SimpleNamespace(get_poses=lambda: truth[kf], timestamps=list(stamps[kf]), frame_index=list(kf))
    return SimpleNamespace(buf=buf, seq=SimpleNamespace(timestamps=stamps), frame_motion={}, _filler=lambda fa, fb: filler)


def test_frames_between_keyframes_follow_the_odometry():
    truth = _curve(9)
    kf = [0, 4, 8]
    G = se3_exp([3.0, -1.0, 2.0, 0.1, -0.4, 0.2])  # the odometry's own world frame
    odometry = {i: G @ T for i, T in enumerate(truth)}
    placed = Tracker.trajectory(_slam(truth, kf, odometry), kf).poses
    np.testing.assert_allclose(placed, truth, atol=1e-9)
    interpolated = Tracker.trajectory(_slam(truth, kf, None), kf).poses  # no odometry: in time
    assert np.linalg.norm(interpolated[1:4, :3, 3] - truth[1:4, :3, 3], axis=1).max() > 0.05
    np.testing.assert_allclose(interpolated[kf], truth[kf], atol=1e-9)


def test_a_keyframe_starts_at_the_rigs_velocity_in_time():
    """A rig of constant body twist (1.2 m/s, 0.4 rad/s about a tilted axis), keyframes 0.1 s
    then 0.4 s apart: the start is the true pose at the new time, and not the last keyframe
    step repeated (which lands 0.36 m short here). ``se3_log`` inverts ``se3_exp`` up to
    nearly half a turn."""
    from mcgs_warp.geometry import se3_log
    from mcgs_warp.system.tracker import constant_velocity

    rng = np.random.default_rng(1)
    xi = np.array([1.2, 0.1, -0.05, 0.1, 0.35, 0.15])
    T0 = se3_exp(rng.normal(size=6))
    at = lambda t: T0 @ se3_exp(t * xi)  # noqa: E731
    start = constant_velocity(at(0.5), at(0.6), 0.5, 0.6, 1.0)
    np.testing.assert_allclose(start, at(1.0), atol=1e-9)
    repeated = at(0.6) @ np.linalg.inv(at(0.5)) @ at(0.6)
    assert np.linalg.norm(repeated[:3, 3] - at(1.0)[:3, 3]) > 0.3
    for angle in (0.0, 1e-9, 1e-5, 0.3, 3.0):
        v = rng.normal(size=6)
        v[3:] *= angle / np.linalg.norm(v[3:])
        np.testing.assert_allclose(se3_log(se3_exp(v)), v, atol=1e-9)
