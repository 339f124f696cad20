"""Datasets: our folder format, EuRoC (MAV), KITTI odometry, TUM RGB-D, Waymo Open Dataset v2,
nuScenes, ROS bags, and the built-in synthetic sequence.

:func:`open_sequence` recognizes the folder layout and returns a :class:`Sequence`.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .euroc import EurocSequence, is_euroc
from .kitti import KittiSequence, is_kitti
from .nuscenes import NuScenesSequence, is_nuscenes
from .sequence import Frame, FolderSequence, FolderWriter, Sequence
from .trajectory import Trajectory, read_tum, write_tum
from .tum import TumSequence
from .waymo import WaymoSequence, is_waymo


def open_sequence(path, rig=None, kitti_cameras: str = "grey", sync_tolerance: float | None = None, rig_source=None, segment: str | None = None, waymo_cameras: str = "front3") -> Sequence:
    """Open a sequence: a ROS 1 ``.bag`` or ROS 2 bag folder (needs ``rig``, whose cameras name
    their ``topic``), or a folder: ours (``rig.yaml`` + ``timestamps.txt``), EuRoC (``mav0/`` or
    ``cam0/data.csv``), KITTI odometry (``calib.txt`` + ``image_0/``; the grey pair, or
    ``kitti_cameras="colour"``), TUM RGB-D (``rgb.txt``), Waymo Open Dataset v2 (``camera_image/``
    + ``camera_calibration/``; ``waymo_cameras`` ``"front3"`` or ``"all"``) or nuScenes
    (``v1.0-*/`` tables). ``segment`` picks a Waymo segment or a nuScenes scene (an error for any
    other layout). A ``rig`` (:class:`Rig`) given for a folder replaces its calibration: same
    number of cameras and resolutions. ``sync_tolerance`` (s) pairs a bag's cameras;
    ``rig_source`` names the rig's file in errors."""
    from .rosbag import BagSequence, bag_paths
    from .sequence import MAX_SYNC_DT

    path = Path(path)
    if segment is not None and not (path.is_dir() and (is_waymo(path) or is_nuscenes(path))):
        raise InputError(None, "--segment", f"picks a Waymo Open Dataset segment or a nuScenes scene; {path} is neither (camera_image/ + camera_calibration/, or v1.0-*/)")
    if bag_paths(path) is not None:
        if rig is None:
            raise InputError(path, None, "a ROS bag carries no calibration: pass --rig RIG.yaml (each camera with its topic:) or --from-kalibr camchain.yaml")
        return BagSequence(path, rig, MAX_SYNC_DT if sync_tolerance is None else sync_tolerance, rig_source=rig_source)
    if path.is_file():
        raise InputError(path, None, "expected a sequence folder or a ROS bag (.bag file, or a ROS 2 bag folder)")
    if not path.is_dir():
        raise InputError(path, None, "data folder not found")
    if sync_tolerance is not None:
        raise InputError(None, "--sync-tolerance", "pairs the cameras of a ROS bag; folders have their own pairing")
    if rig is not None and is_euroc(path) and not (path / "timestamps.txt").is_file():
        # its reader pairs the cameras with the rig's time offsets: pair with the given rig's
        from .euroc import _mav0, read_sensor

        own = [read_sensor(_mav0(path) / f"cam{i}" / "sensor.yaml", f"cam{i}") for i in (0, 1)]
        _check_replacement(own, rig, rig_source)
        seq = EurocSequence(path, rig)
        _check_body(own, rig, rig_source, seq.groundtruth is not None)
        return seq
    seq = _open_folder(path, kitti_cameras, segment, waymo_cameras)  # the folder's own rig: what a replacement must match
    if rig is not None:
        _check_replacement(seq.rig.cameras, rig, rig_source)
        _check_body(seq.rig.cameras, rig, rig_source, seq.groundtruth is not None)
        if isinstance(seq, TumSequence):  # its time offset moves the frames onto the ground truth's clock
            seq = TumSequence(path, rig)
        seq.rig = rig
    return seq


def _check_replacement(own: list, rig, source) -> None:
    """``rig`` may replace the calibration ``own`` (its cameras): as many cameras, same resolutions."""
    if len(rig) != len(own):
        raise InputError(source, "cameras", f"expected {len(own)} cameras (the sequence's), got {len(rig)}")
    for i, (a, b) in enumerate(zip(rig.cameras, own)):
        if (a.width, a.height) != (b.width, b.height):
            raise InputError(source, f"cameras[{i}].resolution", f"expected {b.width}x{b.height} (the sequence's images), got {a.width}x{a.height}")


def _check_body(own: list, rig, source, has_groundtruth: bool) -> None:
    """Warn where a replacement rig puts camera 0 elsewhere in the body than the folder's rig
    (e.g. a camera-only Kalibr camchain, body = cam0, for a EuRoC folder, body = IMU): the
    ground truth is of the folder's body, so the ATE would compare different frames."""
    import numpy as np

    from ..geometry import pose_distance
    from ..errors import warn

    moved, turned = pose_distance(own[0].T_b_c, rig.cameras[0].T_b_c)
    turned = float(np.degrees(turned))
    if has_groundtruth and (moved > 0.01 or turned > 1.0):
        warn(source, f"camera 0 sits {moved * 100:.1f} cm and {turned:.1f} deg from where the folder's own calibration puts it in the body: "
             "the ground truth is of the folder's body, so the ATE compares different frames (a camera-only Kalibr camchain makes cam0 the body; use camchain-imucam.yaml)")


def _open_folder(path: Path, kitti_cameras: str, segment: str | None = None, waymo_cameras: str = "front3") -> Sequence:
    if (path / "timestamps.txt").is_file() or ((path / "rig.yaml").is_file() and not (path / "rgb.txt").is_file()):  # a TUM folder may hold its rig.yaml
        return FolderSequence(path)
    if is_euroc(path):
        return EurocSequence(path)
    if is_kitti(path):
        return KittiSequence(path, kitti_cameras)
    if is_waymo(path):
        return WaymoSequence(path, segment, waymo_cameras)
    if is_nuscenes(path):
        return NuScenesSequence(path, segment)
    if (path / "rgb.txt").is_file():
        return TumSequence(path)
    if not any(path.iterdir()):
        raise InputError(path, None, "data folder is empty")
    raise InputError(
        path, None, "unrecognized data folder: expected rig.yaml + timestamps.txt (ours), mav0/ (EuRoC), calib.txt + image_0/ (KITTI odometry), rgb.txt (TUM RGB-D), camera_image/ + camera_calibration/ (Waymo v2), v1.0-*/ (nuScenes) or a ROS 2 bag"
    )


__all__ = ["Frame", "FolderSequence", "FolderWriter", "Sequence", "Trajectory", "open_sequence", "read_tum", "write_tum"]
