"""Sequences whose parts disagree (issue 15): timestamps vs images, ground truth vs frames,
EuRoC's two cameras, TUM's rgb vs depth. Errors come through the CLI (one line, exit code 2,
before any SLAM runs); warnings come from opening the sequence (one stderr line, once)."""

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from test_bad_input import small_sequence

from mcgs_warp.cli import main
from mcgs_warp.data import Trajectory, open_sequence, write_tum

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
from test_datasets import make_euroc, make_tum  # noqa: E402
from test_sequence import random_trajectory, write_sequence  # noqa: E402

pytestmark = pytest.mark.slow  # runs the whole system: `pytest -m "not slow"` leaves it out

EUROC_T0 = 1403636579763555584  # ns


def run_cli(capsys, tmp_path, data):
    """``mcgs-slam run`` in this process: exit code and stderr lines."""
    rc = main(["run", "--data", str(data), "--out", str(tmp_path / "out")])
    return rc, capsys.readouterr().err.strip().splitlines()


def assert_one_line_error(rc, err, tmp_path, message):
    assert rc == 2
    assert len(err) == 1, err
    assert err[0].startswith("mcgs-slam run: error: ") and message in err[0]
    assert not (tmp_path / "out").exists()  # failed while opening the sequence, before SLAM


def warning_lines(capsys):
    return capsys.readouterr().err.strip().splitlines()


def test_truncated_timestamps_is_an_error(tmp_path, capsys):
    root = small_sequence(tmp_path / "seq", n=4)
    lines = (root / "timestamps.txt").read_text().splitlines(keepends=True)
    (root / "timestamps.txt").write_text("".join(lines[:2] + lines[3:]))  # the issue: third line deleted
    rc, err = run_cli(capsys, tmp_path, root)
    assert_one_line_error(rc, err, tmp_path, f"{root / 'timestamps.txt'}: lists 3 timestamps but cam0/rgb holds 4 images")


def extra_depth_image(root):
    shutil.copy(root / "cam1" / "depth" / "000002.png", root / "cam1" / "depth" / "000003.png")


def missing_depth_image(root):
    (root / "cam0" / "depth" / "000001.png").unlink()


@pytest.mark.parametrize(
    "breaker, message",
    [
        (extra_depth_image, "timestamps.txt: lists 3 timestamps but cam1/depth holds 4 images"),
        (missing_depth_image, "cam0/depth/000001.png: missing frame 1 of 3 (timestamps.txt lists 3 timestamps but cam0/depth holds 2 images)"),
    ],
)
def test_depth_count_mismatch_is_an_error(tmp_path, capsys, breaker, message):
    root = tmp_path / "seq"
    write_sequence(root, np.random.default_rng(0), n=3, depth=True)
    breaker(root)
    rc, err = run_cli(capsys, tmp_path, root)
    assert_one_line_error(rc, err, tmp_path, message)


def test_groundtruth_outside_the_frames_warns_once(tmp_path, capsys):
    root = tmp_path / "seq"
    _, _, traj = write_sequence(root, np.random.default_rng(1), n=3, depth=False)  # frames at 1.0, 1.1, 1.2 s
    open_sequence(root)
    assert warning_lines(capsys) == []  # ground truth of exactly the frames
    longer = random_trajectory(np.random.default_rng(2), 7)
    stamps = np.array([0.99, 1.0, 1.1, 1.2, 1.215, 1.3, 1.4])  # 0.99 and 1.215 are within 0.02 s
    write_tum(root / "groundtruth.txt", Trajectory(stamps, longer.poses))
    seq = open_sequence(root)
    assert len(seq) == 3 and len(seq.groundtruth) == 7  # a warning, not an error
    err = warning_lines(capsys)
    assert len(err) == 1, err
    assert err[0].startswith(f"warning: {root / 'groundtruth.txt'}: 2 of 7 entries lie outside")


def euroc_stamps(n):
    return tuple(EUROC_T0 + 50_000_000 * k for k in range(n))


def test_euroc_dropped_frames_are_counted(tmp_path, capsys):
    root = make_euroc(tmp_path / "MH_01_easy", stamps=euroc_stamps(12))  # cam1 misses the first frame
    seq = open_sequence(root)
    assert len(seq) == 11
    err = warning_lines(capsys)
    assert len(err) == 1, err
    assert err[0].startswith("warning: ") and "dropped 1 of 12 frames that only one camera has" in err[0]
    assert "cam0/data.csv lists 12, cam1/data.csv lists 11" in err[0]


def test_euroc_more_than_10_percent_dropped_is_an_error(tmp_path, capsys):
    root = make_euroc(tmp_path / "MH_01_easy", stamps=euroc_stamps(12))
    csv = root / "mav0" / "cam1" / "data.csv"
    lines = csv.read_text().splitlines(keepends=True)
    csv.write_text("".join(lines[:5] + lines[6:]))  # cam1 misses another frame: 2 of 12 dropped
    rc, err = run_cli(capsys, tmp_path, root)
    assert_one_line_error(rc, err, tmp_path, "dropped 2 of 12 frames that only one camera has")
    assert "more than 10% do not pair up" in err[0]


def test_tum_rgb_frames_without_depth_are_counted(tmp_path, capsys):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    make_tum(root, n=4)  # frame 2 has no depth: 1 of 4
    seq = open_sequence(root)
    assert len(seq) == 4
    err = warning_lines(capsys)
    assert len(err) == 1, err
    assert err[0].startswith(f"warning: {root / 'depth.txt'}: 1 of 4 rgb frames (rgb.txt) have no depth frame within 0.02 s")


def test_tum_few_rgb_frames_without_depth_are_quiet(tmp_path, capsys):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    make_tum(root, n=10)  # 1 of 10 is not more than 10 %
    open_sequence(root)
    assert warning_lines(capsys) == []
