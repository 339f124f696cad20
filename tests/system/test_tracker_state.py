"""The tracking stage's checkpoint state (:meth:`~mcgs_warp.system.tracker.Tracker.state_arrays`,
:meth:`~mcgs_warp.system.tracker.Tracker.load_state_arrays`) on a tracker of a tiny sequence,
no SLAM run: its books (health, lost and kept keyframes, the constant-velocity carry, the open
lost span) and its filler's motions come back into a fresh tracker as they were saved."""

import json

import numpy as np

from mcgs_warp.buffer import KeyframeBuffer
from mcgs_warp.data import FolderWriter, open_sequence
from mcgs_warp.rig import CameraSpec, Rig
from mcgs_warp.system.config import RunConfig
from mcgs_warp.system.tracker import Tracker


def _tracker(root):
    rig = Rig([CameraSpec("a", "pinhole", 32, 24, (30.0, 30.0, 15.5, 11.5))])
    if not root.exists():
        w = FolderWriter(root, rig)
        for k in range(3):
            w.write_frame(k, [np.full((24, 32, 3), 0.5)])
        w.finish(np.arange(3) * 0.1)
    seq = open_sequence(root)
    cfg = RunConfig()
    return Tracker(seq, cfg, KeyframeBuffer(seq.rig, stride=cfg.tracking.stride, device="cpu"))


def test_the_trackers_books_round_trip_through_its_checkpoint_arrays(tmp_path, capsys):
    saved = _tracker(tmp_path / "seq")
    arrays = saved.state_arrays(tmp_path / "corr")
    assert json.loads(str(arrays["tracker.books"])) == {"health": [], "lost": [], "kept": [], "carried": False, "lost_span": None}
    health = [{"keyframe": 1, "frame": 4, "failure": "no MCBA step accepted"}, {"keyframe": 2, "frame": 6, "failure": None}, {"keyframe": 3, "frame": 9, "failure": "residual"}]
    books = {"health": health, "lost": [3, 4], "kept": [1], "carried": True, "lost_span": [9, 11, 2]}
    arrays.update({"tracker.books": np.array(json.dumps(books)), "filler.frames": np.array([1, 2], np.int64), "filler.motion": np.array([0.25, 0.0125])})

    restored = _tracker(tmp_path / "seq")
    restored.load_state_arrays(arrays, tmp_path / "corr", tmp_path / "checkpoint.npz")
    assert (restored.lost, restored.kept, restored.failures) == ([3, 4], [1], [4, 9])
    assert restored.filler.motion == {1: 0.25, 2: 0.0125}
    again = restored.state_arrays(tmp_path / "corr")
    assert json.loads(str(again["tracker.books"])) == books  # the carry and the open span too
    np.testing.assert_array_equal(again["filler.motion"], [0.25, 0.0125])
    capsys.readouterr()
    restored.close_lost_span()  # the open span is the saved one, and it is said once
    restored.close_lost_span()
    err = capsys.readouterr().err
    assert err.count("tracking lost") == 1 and "frames 9-11 (2 keyframes)" in err
