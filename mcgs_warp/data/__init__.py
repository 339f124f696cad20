"""Datasets: our folder format, EuRoC (MAV), TUM RGB-D, and the built-in synthetic sequence.

:func:`open_sequence` recognizes the folder layout and returns a :class:`Sequence`.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .sequence import Frame, FolderSequence, FolderWriter, Sequence
from .trajectory import Trajectory, read_tum, write_tum


def open_sequence(path, rig_path=None, kitti_cameras: str = "grey") -> Sequence:
    """Open a sequence folder: ours (``rig.yaml`` + ``timestamps.txt``), EuRoC
    (``mav0/`` or ``cam0/data.csv``), KITTI odometry (``calib.txt`` + ``image_0/``; the
    grey pair, or ``kitti_cameras="colour"``) or TUM RGB-D (``rgb.txt``). ``rig_path``
    overrides the TUM calibration."""
    from .euroc import EurocSequence, is_euroc
    from .kitti import KittiSequence, is_kitti
    from .tum import TumSequence

    path = Path(path)
    if not path.is_dir():
        raise InputError(path, None, "data folder not found")
    if (path / "timestamps.txt").is_file() or ((path / "rig.yaml").is_file() and not (path / "rgb.txt").is_file()):  # a TUM folder may hold its rig.yaml
        return FolderSequence(path)
    if is_euroc(path):
        return EurocSequence(path)
    if is_kitti(path):
        return KittiSequence(path, kitti_cameras)
    if (path / "rgb.txt").is_file():
        return TumSequence(path, rig_path)
    if not any(path.iterdir()):
        raise InputError(path, None, "data folder is empty")
    raise InputError(
        path, None, "unrecognized data folder: expected rig.yaml + timestamps.txt (ours), mav0/ (EuRoC), calib.txt + image_0/ (KITTI odometry) or rgb.txt (TUM RGB-D)"
    )


__all__ = ["Frame", "FolderSequence", "FolderWriter", "Sequence", "Trajectory", "open_sequence", "read_tum", "write_tum"]
