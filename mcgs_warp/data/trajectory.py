"""Trajectories in TUM format: one pose per line, ``t tx ty tz qx qy qz qw``
(seconds, metres, unit quaternion x y z w); ``#`` starts a comment. And the one pose
interpolation in time (:func:`bracket`, :func:`interpolate_pose`: linear translation,
spherical-linear rotation) that places frames between keyframes and reads given poses at
frame times."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import matrix_to_quat, pose, quat_to_matrix

MAX_ASSOCIATION_DT = 0.02  # s: a time of one stream and of another this close are one moment (TUM's associate.py)


@dataclass
class Trajectory:
    timestamps: np.ndarray  # [K] s, increasing
    poses: np.ndarray  # [K,4,4] T_w_x (x = rig body or camera), m

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]


def nearest_timestamps(t_a: np.ndarray, t_b: np.ndarray, max_dt: float) -> np.ndarray:
    """For each time in ``t_a`` the index of the nearest time in sorted ``t_b`` within
    ``max_dt`` seconds, or -1."""
    t_a, t_b = np.asarray(t_a, np.float64), np.asarray(t_b, np.float64)
    if len(t_b) == 0:
        return -np.ones(len(t_a), int)
    j = np.clip(np.searchsorted(t_b, t_a), 1, max(len(t_b) - 1, 1)) if len(t_b) > 1 else np.zeros(len(t_a), int)
    if len(t_b) > 1:
        j = np.where(np.abs(t_b[j - 1] - t_a) <= np.abs(t_b[j] - t_a), j - 1, j)
    return np.where(np.abs(t_b[j] - t_a) <= max_dt, j, -1)


def bracket(timestamps, t: float, clamp: bool = True) -> tuple[int, int, float]:
    """The two of increasing ``timestamps`` [K] (s) around time ``t`` (s) and how far ``t``
    lies from the first to the second: ``(a, a + 1, u)`` with ``u`` in [0, 1] (clamped before
    the first time and after the last; without ``clamp``, below 0 or above 1 there: the first
    or last interval extrapolated); ``(0, 0, 0.0)`` for a single time."""
    if len(timestamps) == 1:
        return 0, 0, 0.0
    j = int(np.clip(np.searchsorted(timestamps, t), 1, len(timestamps) - 1))
    u = (t - timestamps[j - 1]) / max(timestamps[j] - timestamps[j - 1], 1e-12)
    return j - 1, j, float(np.clip(u, 0.0, 1.0) if clamp else u)


def interpolate_pose(A: np.ndarray, B: np.ndarray, u: float) -> np.ndarray:
    """The pose [4,4] a fraction ``u`` of the way from ``A`` to ``B``: linear translation,
    spherical-linear rotation."""
    T = np.eye(4)
    T[:3, 3] = (1 - u) * A[:3, 3] + u * B[:3, 3]
    T[:3, :3] = quat_to_matrix(slerp(matrix_to_quat(A[:3, :3]), matrix_to_quat(B[:3, :3]), u))
    return T


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """The unit quaternion [4] a fraction ``u`` of the way from ``q0`` to ``q1`` the shorter
    way round (normalized linear interpolation where they nearly agree)."""
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    return (np.sin((1 - u) * th) * q0 + np.sin(u * th) * q1) / np.sin(th)


def read_tum(path, min_poses: int = 1) -> Trajectory:
    """Read a TUM trajectory, validating every line (errors name file and line)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "trajectory file not found")
    stamps, rows = [], []
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise InputError(path, f"line {lineno}", f"expected 8 numbers 't tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise InputError(path, f"line {lineno}", f"expected numbers, got {line!r}") from None
        if not np.all(np.isfinite(vals)):
            raise InputError(path, f"line {lineno}", "contains NaN or Inf")
        q = np.asarray(vals[4:])
        big = np.abs(q).max()
        if big == 0 or np.linalg.norm(q / big) * big < 1e-6:
            raise InputError(path, f"line {lineno}", "quaternion has zero norm")
        vals[4:] = (q / big).tolist()  # pre-scaled so its norm cannot overflow
        if stamps and vals[0] <= stamps[-1]:
            raise InputError(path, f"line {lineno}", f"timestamps must increase, got {vals[0]} after {stamps[-1]}")
        stamps.append(vals[0])
        rows.append(vals[1:])
    if len(stamps) < min_poses:
        raise InputError(path, None, f"expected at least {min_poses} poses, got {len(stamps)}")
    rows = np.array(rows).reshape(-1, 7)
    return Trajectory(np.array(stamps), pose(rows[:, :3], rows[:, 3:]))


def write_tum(path, traj: Trajectory) -> None:
    """Write a TUM trajectory atomically."""
    from ..io import atomic_write

    q = matrix_to_quat(traj.poses[:, :3, :3]) if len(traj) else np.zeros((0, 4))
    with atomic_write(path) as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, T, qq in zip(traj.timestamps, traj.poses, q):
            x, y, z = T[:3, 3]
            f.write(f"{t:.9f} {x:.9f} {y:.9f} {z:.9f} {qq[0]:.9f} {qq[1]:.9f} {qq[2]:.9f} {qq[3]:.9f}\n")
