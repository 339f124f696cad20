"""Our folder format and TUM trajectories: round trips and clear errors."""

import numpy as np
import pytest

from mcgs_warp.data import FolderSequence, FolderWriter, Trajectory, open_sequence, read_tum, write_tum
from mcgs_warp.errors import InputError
from mcgs_warp.geometry import pose
from mcgs_warp.rig import CameraSpec, Rig


def small_rig():
    return Rig(
        [
            CameraSpec("a", "pinhole", 24, 16, (20.0, 20.0, 11.5, 7.5), (0.01,)),
            CameraSpec("b", "fisheye", 20, 12, (10.0, 10.0, 9.5, 5.5), (0.01, 0.0, 0.0, 0.0)),
        ]
    )


def random_trajectory(rng, n):
    q = rng.normal(size=(n, 4))
    return Trajectory(np.arange(n) * 0.1 + 1.0, pose(rng.normal(size=(n, 3)), q / np.linalg.norm(q, axis=1, keepdims=True)))


def write_sequence(root, rng, n=3, depth=True):
    rig = small_rig()
    w = FolderWriter(root, rig)
    frames = []
    for k in range(n):
        imgs = [rng.uniform(0, 1, (c.height, c.width, 3)) for c in rig.cameras]
        deps = [rng.uniform(0.5, 20, (c.height, c.width)) for c in rig.cameras] if depth else None
        w.write_frame(k, imgs, deps)
        frames.append((imgs, deps))
    traj = random_trajectory(rng, n)
    w.finish(traj.timestamps, traj)
    return rig, frames, traj


def test_folder_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    rig, frames, traj = write_sequence(tmp_path / "seq", rng)
    seq = open_sequence(tmp_path / "seq")
    assert isinstance(seq, FolderSequence) and len(seq) == 3 and len(seq.rig) == 2
    np.testing.assert_allclose(seq.timestamps, traj.timestamps)
    for k in (0, 2, -1):
        f = seq[k]
        imgs, deps = frames[k]
        for i in range(2):
            np.testing.assert_allclose(f.images[i], imgs[i], atol=0.5 / 255 + 1e-6)  # 8-bit PNG
            np.testing.assert_allclose(f.depths[i], deps[i], atol=0.5e-3 + 1e-6)  # millimetres
    np.testing.assert_allclose(seq.groundtruth.poses, traj.poses, atol=1e-8)
    with pytest.raises(IndexError):
        seq[3]


def test_metadata_says_what_the_depth_is(tmp_path, capsys):
    """Depth folders need metadata.yaml (exact and inexact depth run differently, and no
    default is safe); ``depth: none`` ignores them (said once); ``exact`` without depth is an
    error; a folder without depth needs no metadata."""
    rng = np.random.default_rng(3)
    root = tmp_path / "seq"
    write_sequence(root, rng)
    meta = root / "metadata.yaml"
    assert "depth: exact" in meta.read_text()
    assert open_sequence(root).depth_cameras() == [True, True]
    meta.write_text("depth: mono\n")
    seq = open_sequence(root)
    assert seq.depth_cameras() == [True, True] and not seq.depth_exact
    meta.write_text("depth: none\n")
    seq = open_sequence(root)
    assert seq.depth_cameras() == [False, False] and seq[0].depths == [None, None]
    assert "says depth: none, so cam0/depth, cam1/depth are not used" in capsys.readouterr().err
    meta.unlink()
    with pytest.raises(InputError, match=r"metadata.yaml: missing: cam0/depth, cam1/depth hold depth; write 'depth: exact'"):
        open_sequence(root)
    meta.write_text("{}\n")
    with pytest.raises(InputError, match=r"metadata.yaml: depth: missing"):
        open_sequence(root)
    plain = tmp_path / "plain"
    write_sequence(plain, rng, depth=False)
    assert "depth: none" in (plain / "metadata.yaml").read_text()  # the writer says what it wrote
    (plain / "metadata.yaml").unlink()
    assert open_sequence(plain).depth_cameras() == [False, False]
    (plain / "metadata.yaml").write_text("depth: exact\n")
    with pytest.raises(InputError, match=r"metadata.yaml: depth: says exact, but no cam<i>/depth folder"):
        open_sequence(plain)


def test_folder_time_offset_is_said_to_be_unused(tmp_path, capsys):
    from mcgs_warp.rig import load_rig, save_rig

    root = tmp_path / "seq"
    write_sequence(root, np.random.default_rng(4), depth=False)
    rig = load_rig(root / "rig.yaml")
    rig.cameras[1].time_offset = 0.003
    save_rig(rig, root / "rig.yaml")
    open_sequence(root)
    assert "time_offset of b is not used" in capsys.readouterr().err


def test_missing_frame_wrong_size_and_bad_timestamps(tmp_path):
    rng = np.random.default_rng(1)
    root = tmp_path / "seq"
    write_sequence(root, rng, depth=False)
    (root / "cam1" / "rgb" / "000001.png").unlink()
    with pytest.raises(InputError, match=r"cam1/rgb/000001.png: missing frame 1 of 3"):
        FolderSequence(root)
    write_sequence(root, rng, depth=False)
    import cv2

    cv2.imwrite(str(root / "cam0" / "rgb" / "000002.png"), np.zeros((5, 5, 3), np.uint8))
    with pytest.raises(InputError, match=r"cam0/rgb/000002.png: expected image size 24x16, got 5x5"):
        FolderSequence(root)[2]
    (root / "cam0" / "rgb" / "000001.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="could not read image"):
        FolderSequence(root)[1]
    (root / "timestamps.txt").write_text("0.0\n0.2\n0.1\n")
    with pytest.raises(InputError, match=r"timestamps.txt: line 3: timestamps must increase"):
        FolderSequence(root)


def test_unrecognized_and_empty_folders(tmp_path):
    with pytest.raises(InputError, match="data folder is empty"):
        open_sequence(tmp_path)
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(InputError, match="unrecognized data folder"):
        open_sequence(tmp_path)
    with pytest.raises(InputError, match="data folder not found"):
        open_sequence(tmp_path / "missing")


def test_tum_trajectory_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(2)
    traj = random_trajectory(rng, 5)
    write_tum(tmp_path / "t.txt", traj)
    back = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(back.timestamps, traj.timestamps)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-8)
    bad = tmp_path / "bad.txt"
    bad.write_text("0 1 2 3 0 0 0 1\n1 1 2 nan 0 0 0 1\n")
    with pytest.raises(InputError, match=r"bad.txt: line 2: contains NaN"):
        read_tum(bad)
    bad.write_text("0 1 2 3 0 0 1\n")
    with pytest.raises(InputError, match=r"line 1: expected 8 numbers"):
        read_tum(bad)
    bad.write_text("# only a comment\n")
    with pytest.raises(InputError, match="expected at least 2 poses, got 0"):
        read_tum(bad, min_poses=2)


def test_every_nth_frame(tmp_path):
    """``run --every N``: frame k is frame k*N of the folder (images, depth, time), the ground
    truth stays whole, and a step that keeps fewer than two frames or is not a whole number
    is refused naming --every."""
    from mcgs_warp.data.sequence import FrameSelection

    rng = np.random.default_rng(0)
    write_sequence(tmp_path / "seq", rng, n=7)
    seq = open_sequence(tmp_path / "seq")
    sub = FrameSelection(seq, 3)
    assert len(sub) == 3
    np.testing.assert_array_equal(sub.timestamps, seq.timestamps[[0, 3, 6]])
    f = sub[2]
    assert f.index == 2 and f.timestamp == seq.timestamps[6]
    np.testing.assert_array_equal(f.images[0], seq[6].images[0])
    np.testing.assert_array_equal(f.depths[1], seq[6].depths[1])
    assert sub.groundtruth is seq.groundtruth and sub.depth_cameras() == seq.depth_cameras()
    for bad in (0, 7, 2.5):
        with pytest.raises(InputError, match="--every"):
            FrameSelection(seq, bad)


def test_a_part_of_a_sequence(tmp_path):
    """``run --frames A:B``: frames A to B-1 of the folder, numbered from 0, then ``--every`` of
    them; the ground truth and the exact depth stay the folder's frames'. A range outside the
    sequence, with fewer than two frames, or not A:B is refused naming --frames."""
    from mcgs_warp.data.sequence import FrameSelection, parse_frames

    rng = np.random.default_rng(1)
    write_sequence(tmp_path / "seq", rng, n=9)
    seq = open_sequence(tmp_path / "seq")
    assert parse_frames("2:8") == (2, 8) and parse_frames("3:") == (3, None) and parse_frames(":4") == (0, 4) and parse_frames(None) == (0, None)
    sub = FrameSelection(seq, 2, *parse_frames("2:8"))
    np.testing.assert_array_equal(sub.timestamps, seq.timestamps[[2, 4, 6]])
    f = sub[1]
    assert f.index == 1 and f.timestamp == seq.timestamps[4]
    np.testing.assert_array_equal(f.images[1], seq[4].images[1])
    assert sub.groundtruth is seq.groundtruth
    assert len(FrameSelection(seq, 1, *parse_frames("5:"))) == 4
    for bad in ("8:12", "4:4", "6:5", "5:6"):
        with pytest.raises(InputError, match="--frames"):
            FrameSelection(seq, 1, *parse_frames(bad))
    for bad in ("1-5", "a:b", "1:2:3"):
        with pytest.raises(InputError, match="--frames"):
            parse_frames(bad)
