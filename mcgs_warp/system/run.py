"""Running the system on a sequence folder and writing its outputs (the CLI's ``run`` and ``demo``)."""

from __future__ import annotations

import time
from pathlib import Path

from ..data import open_sequence
from ..data.resample import at_processing_resolution
from ..data.sequence import CameraSubset, FrameSelection
from ..data.kalibr import load_any_rig
from ..rig import Rig
from .config import RunConfig, load_run_config
from .outputs import write_outputs
from .slam import SLAM, Progress


CHECKPOINT = "checkpoint.npz"


def run_sequence(data, out, config: RunConfig | str | Path | None = None, cameras=None, kitti_cameras: str = "grey", jdsa: bool | None = None, depth: str | None = None, correspondences: str | None = None, device=None, progress: bool = True, resume: bool = False, stop_after_keyframes: int | None = None, rig=None, sync_tolerance: float | None = None, every: int = 1, frames: tuple[int, int | None] = (0, None), poses=None, refine_poses: bool = False, segment: str | None = None, waymo_cameras: str = "front3") -> dict:
    """Run SLAM on the sequence ``data`` (a folder or a ROS bag) and write everything to
    ``out``; returns the metrics. ``rig`` (a :class:`Rig`, or the path of a rig YAML or of a
    Kalibr camchain) is a bag's calibration, or replaces a folder's. The online state is
    checkpointed to ``out/checkpoint.npz`` after every keyframe; ``resume`` continues an
    interrupted run from it. ``frames`` ``(A, B)`` keeps frames A to B (exclusive; B None: to the end) and of them ``every`` every N-th (:class:`FrameSelection`). ``poses``
    (a TUM file of the rig body's poses, a :class:`Trajectory`, or ``"groundtruth"``) maps from
    given poses instead of tracking (:class:`~mcgs_warp.system.posed_mapping.PosedMapping`);
    ``refine_poses`` lets the refinement adjust them. ``segment`` and ``waymo_cameras`` go to
    :func:`open_sequence` (a Waymo segment or nuScenes scene; Waymo's camera set)."""
    t0 = time.perf_counter()
    cfg = config if isinstance(config, RunConfig) else load_run_config(config)
    if jdsa is not None:
        cfg.tracking.jdsa = jdsa
    if depth is not None:
        cfg.tracking.depth = depth
    if correspondences is not None:
        cfg.tracking.correspondences = correspondences
    rig_source = None
    if rig is not None and not isinstance(rig, Rig):
        rig_source = Path(rig)
        rig = load_any_rig(rig_source)
    seq = open_sequence(data, rig=rig, kitti_cameras=kitti_cameras, sync_tolerance=sync_tolerance, rig_source=rig_source, segment=segment, waymo_cameras=waymo_cameras)
    if cameras is not None:
        seq = CameraSubset(seq, cameras)
    if every != 1 or tuple(frames) != (0, None):
        seq = FrameSelection(seq, every, *frames)
    seq = at_processing_resolution(seq, cfg.tracking.max_width)
    Path(out).mkdir(parents=True, exist_ok=True)
    if poses is None:
        slam = SLAM(seq, cfg, device=device, progress=Progress(progress))
    else:
        from .posed_mapping import PosedMapping

        traj, source = given_trajectory(poses, seq, data)
        slam = PosedMapping(seq, cfg, traj, refine_poses=refine_poses, source=source, device=device, progress=Progress(progress))
    result = slam.run(checkpoint=Path(out) / CHECKPOINT, resume=resume, stop_after_keyframes=stop_after_keyframes)
    return write_outputs(out, slam, result, time.perf_counter() - t0)


def given_trajectory(poses, seq, data) -> tuple:
    """The rig trajectory ``map`` holds and what names it in errors: a TUM file, a
    :class:`Trajectory`, or ``"groundtruth"`` (the sequence's own)."""
    from ..data.trajectory import Trajectory, read_tum
    from ..errors import InputError

    if isinstance(poses, Trajectory):
        return poses, None
    if str(poses) == "groundtruth":
        if seq.groundtruth is None:
            raise InputError(data, "groundtruth", "--poses groundtruth needs the sequence's ground-truth poses; this sequence has none")
        return seq.groundtruth, Path(data) / "groundtruth.txt"
    return read_tum(poses, min_poses=1), Path(poses)
