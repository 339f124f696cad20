"""Checkpoints of the online state (``run --resume``): one ``.npz`` per keyframe with the
small arrays, and beside it the large ones, written only when they change (the factor graph's
correspondence segments, one content-named file per mapped keyframe's depth targets).

Functions of the whole system (:class:`~mcgs_warp.system.slam.SLAM`): each stage saves and
restores its own state (``state_arrays`` / ``load_state_arrays``: the tracker with its parts'
and its trajectory filler's, :class:`~mcgs_warp.system.tracker.Tracker`; the mapper's); this
module adds the keyframe buffer's arrays and the per-keyframe files and writes them together.
The global-BA backend runs after the last checkpoint and has none.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

#: What a checkpoint holds; raise it whenever save_checkpoint's arrays change meaning or names
#: (2: the keyframe buffer's exposures, device priors and JDSA grids; 3: tracking health; 4: the mapping background;
#: 5: per-keyframe depth files beside the checkpoint; 6: the keyframe test's flows; 7: image motion between frames instead, keypoint tracks;
#: 8: the keypoint odometry; 9: the background's cube map, sky masks; 10: MCBA's measured residual noise, kept keyframes;
#: 11: the odometry's two-view frames; 12: their measured steps; 13: keyframes' time-baseline depth;
#: 14: keyframes' sweep depth, the rig pairs' behind the time sweep; 15: the tracker's books and the filler's motions
#: as the stages' own arrays, tracker.books and filler.*, no longer in meta), so that
#: --resume refuses an older checkpoint by name instead of failing on a missing array.
CHECKPOINT_FORMAT = 15


def save_checkpoint(slam, path, next_frame: int, kf_frames: list) -> None:
    """Write the whole online state atomically (``path``: a .npz file). The large parts
    live beside it and are written only when they change, so a run's checkpoint I/O grows
    with the keyframes, not with their square: the factor graph's correspondences in
    segment files (:func:`correspondence_store`), each mapped keyframe's full-resolution
    depth targets and placement depth in a file named by its content (:func:`keyframe_store`)."""
    import json

    from ..io import atomic_write

    buf, K = slam.buf, len(slam.buf)
    arrays = {f"mapper.{k}": v for k, v in slam.mapper.state_arrays().items()}
    arrays.update(
        poses=buf.poses.numpy()[:K].copy(),
        disp=buf.disp.numpy()[:K].copy(),
        depth_prior=buf.depth_prior[:K].numpy().copy(),
        prior_conf=buf.prior_conf[:K].numpy().copy(),
        scales=buf.scales[:K].numpy().copy(),
        exposure=buf.exposure.numpy()[:K].copy(),
        timestamps=np.array(buf.timestamps),
        frame_index=np.array(buf.frame_index, dtype=np.int64),
        kf_frames=np.array(kf_frames, dtype=np.int64),
        **slam.tracker.state_arrays(correspondence_store(path)),
        mapped_keys=np.array(sorted(slam.mapper.placed), dtype=np.int64),
        keyframe_files=np.array(_save_keyframe_files(slam, keyframe_store(path)), dtype=str).reshape(-1),
        meta=np.array(json.dumps({"format": CHECKPOINT_FORMAT, "next_frame": next_frame, "config": slam.cfg.to_dict(), "n_frames": len(slam.seq), "seconds": slam.seconds})),
    )
    with atomic_write(path, "wb") as f:
        np.savez(f, **arrays)
    slam.tracker.graph.prune_store(correspondence_store(path))  # segments only the replaced checkpoint used
    keep = set(arrays["keyframe_files"].tolist())
    for old in keyframe_store(path).glob("kf*.npz"):
        if old.name not in keep:
            old.unlink(missing_ok=True)

def _save_keyframe_files(slam, store: Path) -> list:
    """One file per mapped keyframe (``kf<k>_<content digest>.npz``: ``targets_cam<c>``,
    the full-resolution mapping depth targets, none for exact sensor depth, which is
    re-read; ``mapped_depth`` [C,h,w]; ``sweep_depth_cam<c>``, the tracker's sweep
    depth where it has one); a file already there is not written again."""
    import hashlib

    from ..io import atomic_write

    store.mkdir(parents=True, exist_ok=True)
    names = []
    for k in sorted(slam.mapper.placed):
        arrays = {f"targets_cam{c}": np.asarray(slam.buf.targets[k][c] if not slam.tracker.exact_depth else np.zeros(0), np.float32) for c in range(len(slam.seq.rig))}
        arrays["mapped_depth"] = np.asarray(slam.mapper.placed[k], np.float64)
        for c, d in enumerate(slam.tracker.depth_targets.sweeps.get(k, [])):
            arrays[f"sweep_depth_cam{c}"] = d
        digest = hashlib.blake2b(digest_size=10)
        for v in arrays.values():
            digest.update(np.ascontiguousarray(v).tobytes())
        name = f"kf{k:05d}_{digest.hexdigest()}.npz"
        if not (store / name).is_file():
            with atomic_write(store / name, "wb") as f:
                np.savez(f, **arrays)
        names.append(name)
    return names

def load_checkpoint(slam, path) -> tuple[int, list]:
    """Restore the state saved by :meth:`save_checkpoint`; returns (next frame, keyframe frames)."""
    import json

    import warp as wp

    from ..errors import InputError

    try:
        with np.load(path, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        meta = json.loads(str(a["meta"]))
    except (OSError, ValueError, KeyError) as e:
        raise InputError(path, None, f"unreadable checkpoint ({e})") from None
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise InputError(path, None, f"checkpoint was written by an older version (format {meta.get('format', 1)}, this version reads {CHECKPOINT_FORMAT}); start without --resume")
    same_frames = "frame_index" in a and "timestamps" in a and all(0 <= int(f) < len(slam.seq) for f in a["frame_index"]) and np.allclose(np.asarray(a["timestamps"], np.float64), np.asarray(slam.seq.timestamps, np.float64)[np.asarray(a["frame_index"], np.int64)], rtol=0, atol=1e-6)
    if meta["config"] != slam.cfg.to_dict() or meta["n_frames"] != len(slam.seq) or not same_frames:  # same_frames: another --frames range of as many frames
        raise InputError(path, None, "checkpoint was written by a run with another configuration or sequence; start without --resume")
    try:  # the format is the current one: a missing array means a damaged file
        buf = slam.buf
        for k, fi in enumerate(a["frame_index"]):
            frame = slam.seq[int(fi)]
            buf.add(int(fi), float(a["timestamps"][k]), frame.images, np.eye(4), a["disp"][k], depth_prior=a["depth_prior"][k], prior_conf=a["prior_conf"][k])
        wp.copy(buf.poses, wp.array(a["poses"], dtype=wp.transform, device=buf.device), count=len(a["poses"]))
        grids = buf.scales.numpy()
        grids[: len(a["scales"])] = a["scales"]
        buf.scales.assign(grids)
        exposure = buf.exposure.numpy()
        exposure[: len(a["exposure"])] = a["exposure"][: len(exposure)]
        buf.exposure.assign(exposure)
        slam.tracker.load_state_arrays(a, correspondence_store(path), path)
        try:
            files = {}
            for k, name in zip(a["mapped_keys"], a["keyframe_files"]):
                with np.load(keyframe_store(path) / str(name), allow_pickle=False) as z:
                    files[int(k)] = {n: z[n] for n in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise InputError(keyframe_store(path), None, f"unreadable checkpoint keyframe file ({e}); start without --resume") from None
        slam.mapper.placed = {k: f["mapped_depth"] for k, f in files.items()}
        slam.tracker.depth_targets.sweeps = {k: [f[f"sweep_depth_cam{c}"] for c in range(len(slam.seq.rig))] for k, f in files.items() if "sweep_depth_cam0" in f}
        if not slam.tracker.exact_depth:  # estimated targets: restore them as they were
            depths = {k: [f[f"targets_cam{c}"] for c in range(len(slam.seq.rig))] for k, f in files.items()}
        else:
            depths = {k: slam.tracker.mapping_depths(slam.seq[int(fi)], k) for k, fi in enumerate(a["frame_index"])}
        slam.mapper.load_state_arrays({k[7:]: v for k, v in a.items() if k.startswith("mapper.")}, depths)
        slam.seconds = meta["seconds"]
        kf_frames = [int(v) for v in a["kf_frames"]]
    except KeyError as e:
        raise InputError(path, None, f"unreadable checkpoint (no array {e}); start without --resume") from None
    return int(meta["next_frame"]), kf_frames



def keyframe_store(checkpoint) -> Path:
    """The folder beside a checkpoint ``.npz`` that holds its per-keyframe files
    (``out/checkpoint.npz`` -> ``out/checkpoint.keyframes/``)."""
    return Path(checkpoint).with_suffix(".keyframes")


def correspondence_store(checkpoint) -> Path:
    """The folder beside a checkpoint ``.npz`` that holds its correspondence segments
    (``out/checkpoint.npz`` -> ``out/checkpoint.corr/``)."""
    return Path(checkpoint).with_suffix(".corr")
