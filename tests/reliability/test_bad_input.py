"""Bad input through the command line: one clear line, exit code 2, no traceback;
and atomic writes that never leave a truncated file."""

import subprocess
import sys

import numpy as np
import pytest

from mcgs_warp.data import FolderWriter, Trajectory
from mcgs_warp.geometry import pose
from mcgs_warp.io import atomic_write
from mcgs_warp.rig import CameraSpec, Rig


def cli(*args):
    return subprocess.run([sys.executable, "-m", "mcgs_warp", *map(str, args)], capture_output=True, text=True)


def small_sequence(root, n=3):
    rig = Rig([CameraSpec("a", "pinhole", 32, 24, (30.0, 30.0, 15.5, 11.5))])
    w = FolderWriter(root, rig)
    for k in range(n):
        w.write_frame(k, [np.full((24, 32, 3), 0.5)])
    w.finish(np.arange(n) * 0.1)
    return root


def break_rig(root):
    (root / "rig.yaml").write_text("cameras:\n  - model: pinhole\n    resolution: [32, 24]\n    intrinsics: [30, 30, 15.5]\n")


def break_image(root):
    import cv2

    cv2.imwrite(str(root / "cam0" / "rgb" / "000001.png"), np.zeros((5, 5, 3), np.uint8))


def break_timestamps(root):
    (root / "timestamps.txt").write_text("0.0\n0.2\n0.1\n")


def drop_frame(root):
    (root / "cam0" / "rgb" / "000002.png").unlink()


@pytest.mark.parametrize(
    "breaker, message",
    [
        (break_rig, "rig.yaml: cameras[0].intrinsics: expected 4 numbers, got 3"),
        (break_image, "000001.png: expected image size 32x24, got 5x5"),
        (break_timestamps, "timestamps.txt: line 3: timestamps must increase"),
        (drop_frame, "000002.png: missing frame 2 of 3"),
    ],
)
def test_run_on_broken_sequences(tmp_path, breaker, message):
    root = small_sequence(tmp_path / "seq")
    breaker(root)
    res = cli("run", "--data", root, "--out", tmp_path / "out")
    assert res.returncode == 2, res.stderr
    assert message in res.stderr and "Traceback" not in res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("mcgs-slam run: error: ") and message in last  # the error is one line


def test_run_config_errors_and_camera_selection(tmp_path):
    root = small_sequence(tmp_path / "seq")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("tracking:\n  windows: 4\n")
    res = cli("run", "--data", root, "--out", tmp_path / "out", "--config", cfg)
    assert res.returncode == 2 and "cfg.yaml: tracking.windows: unknown key" in res.stderr
    cfg.write_text("mapping:\n  lr_means: -1\n")
    res = cli("run", "--data", root, "--out", tmp_path / "out", "--config", cfg)
    assert res.returncode == 2 and "mapping.lr_means: expected a non-negative number" in res.stderr
    cfg.write_text("tracking:\n  stride: 0\n")  # was a ZeroDivisionError traceback
    res = cli("run", "--data", root, "--out", tmp_path / "out", "--config", cfg)
    assert res.returncode == 2 and "cfg.yaml: tracking.stride: expected at least 1" in res.stderr and "Traceback" not in res.stderr
    res = cli("run", "--data", root, "--out", tmp_path / "out", "--cameras", "0,3")
    assert res.returncode == 2 and "--cameras: camera index 3 out of range" in res.stderr
    res = cli("--debug", "run", "--data", tmp_path / "nowhere", "--out", tmp_path / "out")
    assert res.returncode != 0 and "Traceback" in res.stderr  # --debug shows it


def test_eval_on_bad_trajectories(tmp_path):
    good = Trajectory(np.arange(5) * 0.1, pose(np.random.default_rng(0).normal(size=(5, 3)), np.tile([0, 0, 0, 1.0], (5, 1))))
    from mcgs_warp.data import write_tum

    write_tum(tmp_path / "gt.txt", good)
    (tmp_path / "nan.txt").write_text("0 0 0 nan 0 0 0 1\n")
    res = cli("eval", "--est", tmp_path / "nan.txt", "--gt", tmp_path / "gt.txt")
    assert res.returncode == 2 and "nan.txt: line 1: contains NaN or Inf" in res.stderr
    (tmp_path / "two.txt").write_text("0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n")
    res = cli("eval", "--est", tmp_path / "two.txt", "--gt", tmp_path / "gt.txt")
    assert res.returncode == 2 and "expected at least 3 poses, got 2" in res.stderr
    (tmp_path / "far.txt").write_text("".join(f"{100 + k} 0 0 0 0 0 0 1\n" for k in range(4)))
    res = cli("eval", "--est", tmp_path / "far.txt", "--gt", tmp_path / "gt.txt")
    assert res.returncode == 2 and "match ground-truth timestamps" in res.stderr and "Traceback" not in res.stderr


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
    path = tmp_path / "metrics.json"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_write(path) as f:
            f.write("half of the new con")
            raise RuntimeError("interrupted")
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]  # no temporary left behind
    with atomic_write(path) as f:
        f.write("new")
    assert path.read_text() == "new"


def config_error(tmp_path, text: str, message: str):
    """Write ``text`` as a run configuration and check that loading it fails with ``message``
    (literal); returns the file."""
    import re

    from mcgs_warp.errors import InputError
    from mcgs_warp.system.config import load_run_config

    path = tmp_path / "run.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=re.escape(message)):
        load_run_config(path)
    return path


@pytest.mark.parametrize("text, message", [
    ("tracking:\n  window: 0\n", "tracking.window: expected at least 2"),  # was an IndexError
    ("tracking:\n  window: 1\n", "tracking.window: expected at least 2"),  # silently no tracking
    ("tracking:\n  huber_px: 0\n", "tracking.huber_px: expected more than 0"),  # every residual weight 0
    ("tracking:\n  mcba_iterations: 0\n", "tracking.mcba_iterations: expected at least 1"),
    ("tracking:\n  temporal_radius: 0\n", "tracking.temporal_radius: expected at least 1"),
    ("mapping:\n  insert_stride: 0\n", "mapping.insert_stride: expected at least 1"),
    ("tracking:\n  stereo:\n    planes: 1\n", "tracking.stereo.planes: expected at least 2"),
    ("tracking:\n  stereo:\n    radius: 0\n", "tracking.stereo.radius: expected at least 1"),
    ("tracking:\n  odometry:\n    window: 1\n", "tracking.odometry.window: expected at least 2"),
    ("tracking:\n  keypoint_matching:\n    keyframes: 0\n", "tracking.keypoint_matching.keyframes: expected at least 1"),
    ("tracking:\n  graph:\n    sample: 0\n", "tracking.graph.sample: expected at least 1"),
])
def test_run_config_rejects_values_that_switch_a_stage_off(tmp_path, text, message):
    from mcgs_warp.system.config import load_run_config

    path = config_error(tmp_path, text, message)
    path.write_text(text.replace(": 0\n", ": 2\n").replace(": 1\n", ": 2\n"))
    load_run_config(path)  # the smallest sensible value passes


@pytest.mark.parametrize("value, message", [("0", "expected more than 0"), ("1", "expected less than 1"), ("1.5", "expected less than 1")])
def test_run_config_rejects_an_opacity_outside_zero_and_one(tmp_path, value, message):
    from mcgs_warp.errors import InputError
    from mcgs_warp.system.config import load_run_config

    path = tmp_path / "run.yaml"
    path.write_text(f"mapping:\n  fill_opacity: {value}\n")
    with pytest.raises(InputError, match=f"mapping.fill_opacity: {message}"):
        load_run_config(path)
    path.write_text("mapping:\n  fill_opacity: 0.5\n")
    assert load_run_config(path).mapping.fill_opacity == 0.5


def test_a_cpu_run_names_its_device_once_without_warps_driver_warning(tmp_path):
    """Warp's native start-up prints a CUDA-driver warning on every machine without a GPU: the
    command line keeps that line out and says once, when done, which device ran; a device the
    machine lacks is one clear error."""
    import warp as wp

    res = cli("synth", "--out", tmp_path / "s", "--frames", 2, "--cameras", 1)
    assert res.returncode == 0, res.stderr
    assert "Could not find or load the NVIDIA CUDA driver" not in res.stderr
    assert res.stderr.count("Warp kernels ran on") == 1 and res.stderr.strip().splitlines()[-1].startswith("mcgs-slam synth: Warp kernels ran on"), res.stderr
    if not wp.is_cuda_available():
        assert "Warp kernels ran on cpu (no CUDA driver" in res.stderr
        bad = cli("--device", "cuda:0", "synth", "--out", tmp_path / "t", "--frames", 2, "--cameras", 1)
        assert bad.returncode == 2 and "--device: expected a Warp device of this machine (cpu), got 'cuda:0'" in bad.stderr, bad.stderr


@pytest.mark.parametrize("text, message", [
    ("tracking:\n  stereo:\n    planes_: 64\n", "tracking.stereo.planes_: unknown key (expected one of far, lr_px, max_cost"),
    ("tracking:\n  stereo: 64\n", "tracking.stereo: expected a mapping, got int"),
    ("tracking:\n  stereo:\n    max_ratio: 1.5\n", "tracking.stereo.max_ratio: expected at most 1.0"),
    ("tracking:\n  keypoint_matching:\n    min_inliers: 3\n", "tracking.keypoint_matching.min_inliers: expected at least 4"),
    ("tracking:\n  graph:\n    max_per_view: 6\n", "tracking.graph.max_per_view: not settable: tracking.temporal_radius sets it"),
])
def test_nested_stage_sections_are_validated_like_the_others(tmp_path, text, message):
    config_error(tmp_path, text, message)


def test_every_stage_section_reaches_its_stage(tmp_path):
    """tracking.stereo / keypoint_matching / odometry / flow / graph set from YAML are what the
    tracker's parts run with (the keypoint matching for both keypoint trackers), and the
    resolved config.yaml a run writes loads back to the same configuration."""
    import dataclasses

    import yaml

    from mcgs_warp.buffer import KeyframeBuffer
    from mcgs_warp.data import open_sequence
    from mcgs_warp.system.config import load_run_config
    from mcgs_warp.system.tracker import Tracker

    path = tmp_path / "run.yaml"
    path.write_text("tracking:\n  temporal_radius: 3\n  stereo:\n    planes: 64\n    radius: 2\n  keypoint_matching:\n    features: 500\n"
                    "  odometry:\n    window: 7\n  graph:\n    min_overlap: 0.2\n  flow:\n    patch_size: 6\n    sigma: 2.0\n")
    cfg = load_run_config(path)
    seq = open_sequence(small_sequence(tmp_path / "seq"))
    tracker = Tracker(seq, cfg, KeyframeBuffer(seq.rig, stride=cfg.tracking.stride))
    assert tracker.stereo.cfg.planes == 64 and tracker.stereo.cfg.radius == 2
    assert tracker.keypoints.cfg.features == 500 and tracker.odometry.tracker is tracker.keypoints
    assert tracker.odometry.cfg.window == 7
    assert tracker.flow.settings == ("medium", 0, 6, 5.0) and tracker.flow.sigma == 2.0  # no exact depth here: the flow settings, not the preset
    assert tracker.graph.cfg.min_overlap == 0.2 and tracker.graph.cfg.max_per_view == 6
    (tmp_path / "resolved.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    again = load_run_config(tmp_path / "resolved.yaml")
    assert dataclasses.asdict(again) == dataclasses.asdict(cfg)
