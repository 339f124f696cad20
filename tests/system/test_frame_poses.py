"""The frames between keyframes (:class:`~mcgs_warp.system.trajectory_filler.TrajectoryFiller`):
placed by the keypoint odometry (moved by the keyframes' correction) where it tracked the span,
else interpolated in time, without the time the rig stood still; and a new keyframe's start
at constant velocity."""

from types import SimpleNamespace

import numpy as np

from mcgs_warp.geometry import se3_exp
from mcgs_warp.system.trajectory_filler import TrajectoryFiller, constant_velocity


def _curve(n):
    """A car turning and braking: rig poses [n,4,4] at 10 Hz."""
    poses, T = [], np.eye(4)
    for i in range(n):
        poses.append(T.copy())
        T = T @ se3_exp([0.0, 0.0, 1.5 - 0.12 * i, 0.0, 0.12, 0.0])  # forward, slowing, yawing
    return np.stack(poses)


def _keyframes(poses, stamps, frames):
    """The parts of a keyframe buffer that the filler reads: keyframe poses, times and frames."""
    return SimpleNamespace(get_poses=lambda: poses, timestamps=list(stamps), frame_index=list(frames))


def _filler(truth, kf, placed):
    """A filler of frames at 10 Hz with keyframes ``kf`` at their true poses, the frames
    between placed by ``placed`` (or not: None)."""
    stamps = 0.1 * np.arange(len(truth))
    return TrajectoryFiller(_keyframes(truth[kf], stamps[kf], kf), stamps, lambda fa, fb: placed)


def test_frames_between_keyframes_follow_the_odometry():
    truth = _curve(9)
    kf = [0, 4, 8]
    G = se3_exp([3.0, -1.0, 2.0, 0.1, -0.4, 0.2])  # the odometry's own world frame
    odometry = {i: G @ T for i, T in enumerate(truth)}
    placed = _filler(truth, kf, odometry).trajectory().poses
    np.testing.assert_allclose(placed, truth, atol=1e-9)
    interpolated = _filler(truth, kf, None).trajectory().poses  # no odometry: in time
    assert np.linalg.norm(interpolated[1:4, :3, 3] - truth[1:4, :3, 3], axis=1).max() > 0.05
    np.testing.assert_allclose(interpolated[kf], truth[kf], atol=1e-9)


def test_frames_between_keyframes_skip_the_time_the_rig_stood_still():
    """Keyframes at frames 0 and 5; the rig stood still over frames 1-3 (no image motion
    since the frame before) and then moved: frames 1-3 stay at keyframe 0 and frame 4 lies
    half way (half the moving time). Interpolating in time would put them at 1/5 .. 4/5. When
    every frame moved, or a motion is unknown, it is plain time interpolation."""
    T0, T5 = np.eye(4), np.eye(4)
    T5[:3, 3] = [2.0, 0.0, 0.0]
    filler = TrajectoryFiller(_keyframes(np.stack([T0, T5]), [0.0, 0.5], [0, 5]), np.arange(6) * 0.1, lambda fa, fb: None)  # no keypoint odometry
    for f, m in {1: 0.001, 2: 0.0005, 3: 0.001, 4: 0.05, 5: 0.05}.items():
        filler.record(f, m)
    x = filler.trajectory().positions[:, 0]
    np.testing.assert_allclose(x, [0.0, 0.0, 0.0, 0.0, 1.0, 2.0], atol=1e-12)
    # steady motion; uneven motion (a car turning: parallax and rotation); no motions
    for motions in ({1: 0.02, 2: 0.02, 3: 0.02, 4: 0.02, 5: 0.02}, {1: 0.05, 2: 0.012, 3: 0.03, 4: 0.015, 5: 0.02}, {}):
        filler.motion = dict(motions)
        np.testing.assert_allclose(filler.trajectory().positions[:, 0], [0.0, 0.4, 0.8, 1.2, 1.6, 2.0], atol=1e-12)


def test_a_keyframe_starts_at_the_rigs_velocity_in_time():
    """A rig of constant body twist (1.2 m/s, 0.4 rad/s about a tilted axis), keyframes 0.1 s
    then 0.4 s apart: the start is the true pose at the new time, and not the last keyframe
    step repeated (which lands 0.36 m short here). ``se3_log`` inverts ``se3_exp`` up to
    nearly half a turn."""
    from mcgs_warp.geometry import se3_log

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


def test_the_fillers_motions_round_trip_through_its_checkpoint_arrays():
    """A resumed run's filler places the frames as the interrupted one would: the recorded
    motions (a pause over frames 1-3) come back exactly, and with them the paused poses."""
    T5 = np.eye(4)
    T5[:3, 3] = [2.0, 0.0, 0.0]
    keyframes, stamps = _keyframes(np.stack([np.eye(4), T5]), [0.0, 0.5], [0, 5]), np.arange(6) * 0.1
    saved = TrajectoryFiller(keyframes, stamps, lambda fa, fb: None)
    for f, m in {1: 0.001, 2: 0.0005, 3: 1 / 3 * 0.003, 4: 0.05, 5: 0.05}.items():
        saved.record(f, m)
    arrays = saved.state_arrays()
    np.testing.assert_array_equal(arrays["filler.frames"], [1, 2, 3, 4, 5])
    restored = TrajectoryFiller(keyframes, stamps, lambda fa, fb: None)
    restored.load_state_arrays(arrays)
    assert restored.motion == saved.motion and all(type(m) is float for m in restored.motion.values())
    np.testing.assert_allclose(restored.trajectory().positions[:, 0], [0.0, 0.0, 0.0, 0.0, 1.0, 2.0], atol=1e-12)
