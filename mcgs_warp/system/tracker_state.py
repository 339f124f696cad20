"""The tracking stage's checkpoint state (:meth:`~mcgs_warp.system.tracker.Tracker.state_arrays`,
:meth:`~mcgs_warp.system.tracker.Tracker.load_state_arrays`; written with the rest of the online
state by :mod:`.checkpoint`): its parts' arrays (the factor graph's, whose correspondences go to
segment files in a folder; the keypoint tracks', the keypoint odometry's, MCBA's measured noise,
the trajectory filler's) and its own books as JSON in ``tracker.books`` (every solve's health,
:mod:`.health`; the lost and kept keyframes, whether the last one kept the constant-velocity
prediction, the open lost span, :mod:`.lost_tracking`). Keypoints are not stored:
:func:`load_state_arrays` detects them again. The mapping depth targets
(:attr:`~mcgs_warp.system.tracker.Tracker.depth_targets`) travel per keyframe beside the
checkpoint (:mod:`.checkpoint`).
"""

from __future__ import annotations

import json
import zipfile

import numpy as np


def state_arrays(tracker, store) -> dict:
    """``tracker``'s state for a checkpoint (``np.savez``; ``store``: the folder of its
    correspondence segments)."""
    books = {"health": tracker.checks.records, **tracker.lost_tracking.state()}
    return {**tracker.graph.state_arrays(store), **(tracker.tracks.state_arrays() if tracker.tracks is not None else {}),
            **(tracker.odometry.state_arrays() if tracker.odometry is not None else {}), **tracker.mcba.state_arrays(),
            **tracker.filler.state_arrays(), "tracker.books": np.array(json.dumps(books))}


def load_state_arrays(tracker, a: dict, store, source) -> None:
    """Restore :func:`state_arrays` (``store``: its correspondence folder) into ``tracker``,
    whose keyframe buffer holds the saved keyframes; the keypoints of every keyframe and of
    the odometry's recent frames are detected again (deterministic from the images). A
    missing array raises KeyError; tracks or correspondences that do not fit raise
    :class:`~mcgs_warp.errors.InputError` naming ``source`` (the checkpoint) or ``store``."""
    from ..errors import InputError

    seq = tracker.seq

    def detect(i):
        return tracker.keypoints.detect(seq[i].images, seq[i].depths if tracker.exact_depth else None)

    if tracker.keypoints is not None:
        for k, i in enumerate(tracker.buf.frame_index):
            views = detect(int(i))
            tracker.keyframe_views[k] = views
            if tracker.tracks is not None:
                tracker.tracks.add_views(k, views)
    try:
        if tracker.tracks is not None:
            tracker.tracks.load_state_arrays(a)
    except ValueError as e:
        raise InputError(source, "tracks.parent", f"{e}; start without --resume") from None
    try:
        if tracker.odometry is not None:
            tracker.odometry.load_state_arrays(a, detect)
    except ValueError as e:
        raise InputError(source, "odometry.tracks.parent", f"{e}; start without --resume") from None
    tracker.mcba.load_state_arrays(a)
    try:
        tracker.graph.load_state_arrays(a, store)
    except (OSError, ValueError, KeyError, IndexError, EOFError, zipfile.BadZipFile) as e:
        raise InputError(store, None, f"unreadable checkpoint correspondences ({e}); start without --resume") from None
    tracker.filler.load_state_arrays(a)
    books = json.loads(str(a["tracker.books"]))
    tracker.checks.records = books["health"]
    tracker.lost_tracking.load_state(books)
