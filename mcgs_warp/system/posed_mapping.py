"""Mapping from given poses (``mcgs-slam map``): the system's depth estimation, Gaussian
mapping and refinement with the rig poses held at a trajectory the user already has (GNSS/INS,
LiDAR odometry, a sequence's ground truth).

Keyframes are chosen as in a run; each starts at its given pose, and MCBA (+ JDSA) solves
only the depths (every pose of the window held), online and in the offline global BA. The
refinement adjusts the poses only with ``refine_poses``. There is no keypoint tracking and no
relocalization. Frames between keyframes take their given poses (moved by the keyframes'
refinement, if any). With the ground truth it measures the mapping alone: the map's ceiling
beside every tracking result.

Poses are the rig body's ``T_w_b`` (TUM: ``t tx ty tz qx qy qz qw``), interpolated to each
frame's time as a run's frames between keyframes are
(:func:`~mcgs_warp.data.trajectory.interpolate_pose`: linear translation, slerp rotation; a
frame more than ``max_dt`` outside the trajectory is an error). The map and the written
trajectory are in the first frame's rig frame, as a run's (GNSS coordinates far from the
origin would cost float32 precision).
"""

from __future__ import annotations

import numpy as np

from ..data.trajectory import Trajectory, bracket, interpolate_pose
from ..errors import InputError
from ..geometry import invert
from .config import RunConfig
from .slam import SLAM
from .tracker import Tracker


def poses_at(traj: Trajectory, stamps, source, max_dt: float = 0.02) -> np.ndarray:
    """[N,4,4] poses of ``traj`` at times ``stamps`` [N] (s), interpolated; ``source`` names
    the trajectory in errors."""
    t = np.asarray(traj.timestamps, np.float64)
    stamps = np.asarray(stamps, np.float64)
    out = np.zeros((len(stamps), 4, 4))
    for n, s in enumerate(stamps):
        if s < t[0] - max_dt or s > t[-1] + max_dt:
            raise InputError(source, None, f"frame {n} at t = {s:.6f} s lies outside the given poses ({t[0]:.6f}-{t[-1]:.6f} s, tolerance {max_dt} s)")
        a, b, u = bracket(t, s)
        out[n] = traj.poses[a] if a == b else interpolate_pose(traj.poses[a], traj.poses[b], u)
    return out


class PosedTracker(Tracker):
    """The tracking stage with the rig poses given (``given`` [N,4,4] per frame): each keyframe
    starts at its pose and MCBA holds every pose of the window, so it solves only the depths."""

    def __init__(self, sequence, config: RunConfig, buffer, given: np.ndarray):
        self.given = given
        super().__init__(sequence, config, buffer)

    def given_pose(self, index: int):
        return self.given[index]

    def held(self, keyframes):
        return set(int(k) for k in keyframes)

    def _recover(self, k, window, T_init, disp0, why) -> bool:
        """A weak depth solve keeps its given pose: nothing to relocalize."""
        return True

    def frame_poses(self, fa: int, fb: int):
        return self.given


class PosedMapping(SLAM):
    """The SLAM pipeline with the rig poses given (module docstring). ``poses``: the rig
    body's trajectory; ``source``: where it came from (errors name it)."""

    def __init__(self, sequence, config: RunConfig, poses: Trajectory, refine_poses: bool = False, source=None, device=None, progress=None):
        config.tracking.keypoints = False  # nothing to track or relocalize
        config.refinement.poses = bool(refine_poses)
        given = poses_at(poses, sequence.timestamps, source)
        self.given = invert(given[0])[None] @ given  # in the first frame's rig frame
        super().__init__(sequence, config, device=device, progress=progress)

    def make_tracker(self) -> Tracker:
        return PosedTracker(self.seq, self.cfg, self.buf, self.given)
