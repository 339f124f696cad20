"""Poses of the frames that are not keyframes (DROID-SLAM's ``PoseTrajectoryFiller``): after
the run, every frame's rig pose from the keyframes' (:class:`TrajectoryFiller`); during it, a
new keyframe's start from the last keyframes' motion (:func:`constant_velocity`).

The filler's inputs are the keyframe buffer's poses, times and frames, the poses some other
tracking gave the frames of a span between keyframes (the keypoint odometry's, a given
trajectory's), and each frame's image motion since the frame before, which the tracker
records into it (:meth:`TrajectoryFiller.record`). Its state is those motions; its output
the trajectory of every frame (:meth:`TrajectoryFiller.trajectory`). Poses are interpolated
by :func:`~mcgs_warp.data.trajectory.interpolate_pose`, as given poses are read at frame
times (:mod:`.posed_mapping`).
"""

from __future__ import annotations

import numpy as np

from ..buffer import KeyframeBuffer
from ..data.trajectory import Trajectory, bracket, interpolate_pose
from ..geometry import se3_exp, se3_log

#: rad (1.8 px at a 180 px focal length, 3.7 px at KITTI's 370): less image motion since the frame before
#: is a pause. Chosen on indoor seeds 6 and 10 (camera noise in a still, low-texture corridor reaches
#: 0.006 rad; the slowest drive 0.024); KITTI's frames move 0.028 rad or more.
STILL_MOTION = 0.01


class TrajectoryFiller:
    """Every frame's rig pose from the keyframes' (module docstring). ``timestamps`` [N] (s):
    the sequence's frame times; ``placed(fa, fb)``: poses [frame -> 4x4 T_w_b] that place
    every frame between the keyframes at frames ``fa`` and ``fb`` (in their own world
    frame), or None where nothing did."""

    def __init__(self, buffer: KeyframeBuffer, timestamps, placed):
        self.buf = buffer
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.placed = placed
        self.motion: dict = {}  # frame index -> image motion (rad) since the frame before it (the keyframe test's flows)

    def record(self, index: int, motion: float) -> None:
        """Frame ``index``'s image motion (rad) since the frame before it."""
        self.motion[index] = motion

    def state_arrays(self) -> dict:
        """The filler's state for a checkpoint: the frames with a recorded motion
        (``filler.frames`` [F] int64) and their motions (``filler.motion`` [F] float64, rad)."""
        return {"filler.frames": np.array(list(self.motion), np.int64), "filler.motion": np.array(list(self.motion.values()), np.float64)}

    def load_state_arrays(self, a: dict) -> None:
        """Restore :meth:`state_arrays`."""
        self.motion = {int(i): float(m) for i, m in zip(a["filler.frames"], a["filler.motion"], strict=True)}

    def trajectory(self) -> Trajectory:
        """Rig poses for every frame: keyframes as estimated; a frame between two keyframes
        that ``placed`` places (every frame of the span) is its pose there moved by the
        correction of the keyframe poses, ``T_kf (T_kf^placed)^-1``, interpolated between the
        two keyframes in time (DROID-SLAM's trajectory filler does the same with its own
        tracking). Other frames are interpolated between their keyframes (linear
        translation, spherical-linear rotation) in time, except that
        time the rig stood still does not count: a frame whose image motion since the frame
        before (:meth:`record`) is below :data:`STILL_MOTION` did not move
        (:func:`moving_time`). So a pause stands still, and a drive is plain time
        interpolation (which a car's smooth motion suits: 3 mm off on a straight KITTI
        drive with the true keyframe poses)."""
        T_kf = self.buf.get_poses()
        t_kf = np.array(self.buf.timestamps)
        stamps = self.timestamps
        out = np.zeros((len(stamps), 4, 4))
        placed: dict = {}  # (fa, fb) -> the frame poses that place the frames between, or None
        clocks: dict = {}  # (fa, fb) -> the moving time of the frames between (:func:`moving_time`), or None
        for i, t in enumerate(stamps):
            a, b, u = bracket(t_kf, t)
            fa, fb = self.buf.frame_index[a], self.buf.frame_index[b]
            if fa < i < fb:
                if (fa, fb) not in placed:
                    placed[(fa, fb)] = self.placed(fa, fb)
                src = placed[(fa, fb)]
                if src is not None:
                    out[i] = interpolate_pose(T_kf[a] @ np.linalg.inv(src[fa]), T_kf[b] @ np.linalg.inv(src[fb]), u) @ src[i]
                    continue
                if (fa, fb) not in clocks:  # once per keyframe interval
                    clocks[(fa, fb)] = moving_time(stamps[fa : fb + 1], [self.motion.get(f) for f in range(fa + 1, fb + 1)])
                if clocks[(fa, fb)] is not None:
                    u = float(clocks[(fa, fb)][i - fa])
            out[i] = T_kf[a] if a == b else interpolate_pose(T_kf[a], T_kf[b], u)
        return Trajectory(stamps, out)


def constant_velocity(T_a: np.ndarray, T_b: np.ndarray, t_a: float, t_b: float, t: float) -> np.ndarray:
    """The pose [4,4] at time ``t`` (s) if the rig keeps the body-frame twist it had from
    ``T_a`` (time ``t_a``) to ``T_b`` (``t_b``): keyframes are not evenly spaced in time, and
    repeating the last keyframe step at a gap of another length starts the solve a
    fraction of a step off (facing a tiled wall, where keypoints fail, guided flow then locked
    onto the tile beside the true one: 0.5 m jumps, tests/system/test_wall.py)."""
    rate = (t - t_b) / (t_b - t_a) if t_b > t_a else 1.0
    return T_b @ se3_exp(rate * se3_log(np.linalg.inv(T_a) @ T_b))


def moving_time(stamps, motions, still: float = STILL_MOTION):
    """Fractions [n] of the time from the first to the last of ``stamps`` [n] that the rig
    spent moving, per frame, or None (all frames moved: plain time interpolation; a motion
    is unknown; nothing moved). ``motions`` [n-1]: image motion (rad) of each frame after
    the first since the frame before it; below ``still`` it stood still."""
    if any(m is None for m in motions):
        return None
    moved = np.asarray(motions, np.float64) >= still
    if moved.all() or not moved.any():
        return None
    clock = np.concatenate([[0.0], np.cumsum(np.where(moved, np.diff(np.asarray(stamps, np.float64)), 0.0))])
    return clock / clock[-1]
