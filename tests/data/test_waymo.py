"""Waymo Open Dataset v2 reader on Parquet fixtures (waymo_fixture.py) written with the release's
column names and types (src/waymo_open_dataset/v2/perception/{base,camera_image,context,pose}.py)."""

import sys

import cv2
import numpy as np
import pytest

from mcgs_warp.data import open_sequence
from mcgs_warp.data.waymo import WaymoSequence, is_waymo, waymo_segments
from mcgs_warp.errors import InputError
from mcgs_warp.geometry import invert

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
pc = pytest.importorskip("pyarrow.compute")

from waymo_fixture import H, H_SIDE, NAMES, SEGMENT, T0, W, calibration, image, make_waymo, vehicle_pose  # noqa: E402


def waymo_project(X_w, world_from_vehicle, cam):
    """Waymo's own camera model (wdl_limited/camera/camera_model.cc, CameraToImage +
    DirectionToImage): camera frame x forward, y left, z up; u_n = -y/x, v_n = -z/x."""
    (fu, fv, cu, cv, k1, k2, p1, p2, k3), E = calibration(cam)
    x, y, z = (invert(E) @ invert(world_from_vehicle) @ np.append(X_w, 1.0))[:3]
    u, v = -y / x, -z / x
    r2 = u * u + v * v
    rd = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3
    und = u * rd + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
    vnd = v * rd + p1 * (r2 + 2 * v * v) + 2 * p2 * u * v
    return np.array([und * fu + cu, vnd * fv + cv])


def our_project(X_w, T_w_b, spec):
    """Our convention: T_w_c = T_w_b @ T_b_c, OpenCV camera axes and distortion (cv2.projectPoints)."""
    T_c_w = invert(T_w_b @ spec.T_b_c)
    fx, fy, cx, cy = spec.intrinsics
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    px, _ = cv2.projectPoints(X_w[None], cv2.Rodrigues(T_c_w[:3, :3])[0], T_c_w[:3, 3], K, np.array(spec.distortion))
    return px[0, 0]


def test_front3_rig_poses_images_and_projection(tmp_path):
    root = make_waymo(tmp_path / "training")
    assert is_waymo(root) and waymo_segments(root) == [SEGMENT]
    seq = open_sequence(root)
    assert isinstance(seq, WaymoSequence) and seq.name == SEGMENT and len(seq) == 4
    assert [c.name for c in seq.rig.cameras] == ["FRONT_LEFT", "FRONT", "FRONT_RIGHT"]
    np.testing.assert_allclose(seq.timestamps, (T0 + 100_000 * np.arange(4)) * 1e-6, rtol=0, atol=1e-9)
    for k in range(4):
        np.testing.assert_allclose(seq.groundtruth.poses[k], vehicle_pose(k), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(seq.groundtruth.timestamps, seq.timestamps)
    for spec, cam in zip(seq.rig.cameras, (2, 1, 3)):
        intr, E = calibration(cam)
        assert spec.intrinsics == intr[:4] and spec.distortion == intr[4:] and (spec.width, spec.height) == (W, H)
        np.testing.assert_allclose(spec.T_b_c[:3, 3], E[:3, 3], rtol=0, atol=1e-12)
        # our optical axis (+z) is Waymo's forward (+x), our x (right) its -y, our y (down) its -z
        np.testing.assert_allclose(spec.T_b_c[:3, :3], E[:3, :3] @ [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    # a world point in front of each camera lands on the same pixel in both conventions
    for k in (0, 3):
        T_w_b = seq.groundtruth.poses[k]
        for spec, cam in zip(seq.rig.cameras, (2, 1, 3)):
            X_w = (T_w_b @ spec.T_b_c @ [0.4, -0.3, 9.0, 1.0])[:3]
            uv = waymo_project(X_w, vehicle_pose(k), cam)
            assert 0 < uv[0] < W and 0 < uv[1] < H
            np.testing.assert_allclose(our_project(X_w, T_w_b, spec), uv, rtol=0, atol=1e-3)
    # images: RGB float32 in [0, 1], exactly the decoded JPEGs; read out of order across row groups
    for k in (3, 0, 2, 2, 1):
        f = seq[k]
        assert f.index == k and f.depths == [None] * 3 and f.timestamp == seq.timestamps[k]
        for img, cam in zip(f.images, (2, 1, 3)):
            want = cv2.imdecode(np.frombuffer(image(k, cam), np.uint8), cv2.IMREAD_COLOR)[..., ::-1] / np.float32(255)
            assert img.dtype == np.float32 and img.shape == (H, W, 3)
            np.testing.assert_array_equal(img, want)
    np.testing.assert_allclose(seq.image_timestamps[1], seq.timestamps[1] + 0.01 * np.array([2, 1, 3]), atol=1e-6)


def test_all_five_cameras_and_selection_errors(tmp_path):
    root = make_waymo(tmp_path / "w", row_group_size=1)
    seq = open_sequence(root, waymo_cameras="all")
    assert [c.name for c in seq.rig.cameras] == ["SIDE_LEFT", "FRONT_LEFT", "FRONT", "FRONT_RIGHT", "SIDE_RIGHT"]
    assert [(c.width, c.height) for c in seq.rig.cameras] == [(W, H_SIDE), (W, H), (W, H), (W, H), (W, H_SIDE)]
    assert [img.shape for img in seq[2].images] == [(H_SIDE, W, 3)] + [(H, W, 3)] * 3 + [(H_SIDE, W, 3)]
    with pytest.raises(InputError, match=r"--waymo-cameras: expected one of front3 \| all, got 'front5'"):
        WaymoSequence(root, cameras="front5")
    # a segment without side cameras reads as front3, and says which cameras "all" lacks
    only = make_waymo(tmp_path / "front", cameras=(1, 2, 3))
    assert len(WaymoSequence(only).rig) == 3
    with pytest.raises(InputError, match="no calibration of camera 4 SIDE_LEFT"):
        WaymoSequence(only, cameras="all")


def test_segment_choice(tmp_path):
    root = make_waymo(tmp_path / "w")
    make_waymo(root, segment="other_segment", n=3)
    with pytest.raises(InputError, match=f"--segment NAME.*segments: {SEGMENT}, other_segment"):
        open_sequence(root)
    assert len(open_sequence(root, segment="other_segment")) == 3
    with pytest.raises(InputError, match="nope: no such segment"):
        open_sequence(root, segment="nope")
    (tmp_path / "k").mkdir()
    (tmp_path / "k" / "rgb.txt").write_text("")
    with pytest.raises(InputError, match="--segment: picks a Waymo"):
        open_sequence(tmp_path / "k", segment=SEGMENT)


def test_bad_waymo_folders(tmp_path):
    root = make_waymo(tmp_path / "w")
    calib = root / "camera_calibration" / f"{SEGMENT}.parquet"
    # a missing component file
    data = calib.read_bytes()
    calib.unlink()
    with pytest.raises(InputError, match=f"camera_calibration/{SEGMENT}.parquet: file not found"):
        WaymoSequence(root)
    # a truncated file (a download cut short)
    calib.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="not a readable Parquet file"):
        WaymoSequence(root)
    calib.write_bytes(data)
    # an unknown camera
    path = root / "camera_image" / f"{SEGMENT}.parquet"
    table = pq.read_table(path)
    names = table.column("key.camera_name").to_pylist()
    pq.write_table(table.set_column(2, "key.camera_name", pa.array([7] + names[1:], pa.int8())), path)
    with pytest.raises(InputError, match=r"key.camera_name: unknown camera 7: expected one of 1 FRONT, 2 FRONT_LEFT"):
        WaymoSequence(root)
    # a missing column
    pq.write_table(table.drop_columns(["[CameraImageComponent].image"]), path)
    with pytest.raises(InputError, match=r"\[CameraImageComponent\].image: missing column"):
        WaymoSequence(root)
    # a corrupt image
    images = table.column("[CameraImageComponent].image").to_pylist()
    pq.write_table(table.set_column(3, "[CameraImageComponent].image", pa.array([b"not a jpeg"] + images[1:], pa.binary())), path)
    seq = WaymoSequence(root)
    seq[1]
    with pytest.raises(InputError, match=f"key.frame_timestamp_micros {T0}, camera FRONT: could not decode"):
        seq[0]


def test_camera_names_as_strings_and_dropped_frames(tmp_path, capsys):
    """The repository's own test data stores key.camera_name as the enum's name; a frame that
    lacks a camera is dropped with a warning."""
    root = make_waymo(tmp_path / "w")
    path = root / "camera_image" / f"{SEGMENT}.parquet"
    table = pq.read_table(path)
    names = [NAMES[c] for c in table.column("key.camera_name").to_pylist()]
    table = table.set_column(2, "key.camera_name", pa.array(names, pa.string()))
    front_of_frame_1 = pc.and_(pc.equal(table.column("key.frame_timestamp_micros"), T0 + 100_000), pc.equal(table.column("key.camera_name"), "FRONT"))
    pq.write_table(table.filter(pc.invert(front_of_frame_1)), path)
    seq = WaymoSequence(root)
    assert len(seq) == 3 and "dropped 1 of 4 frames" in capsys.readouterr().err
    np.testing.assert_allclose(seq.groundtruth.poses[2], vehicle_pose(2), atol=1e-9)


def test_without_pyarrow(tmp_path, monkeypatch):
    root = make_waymo(tmp_path / "w")
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
    with pytest.raises(InputError, match=r"needs pyarrow: pip install \.\[waymo\]"):
        open_sequence(root)


def test_cli_options():
    from mcgs_warp.cli import build_parser

    args = build_parser().parse_args(["run", "--data", "d", "--out", "o", "--segment", SEGMENT, "--waymo-cameras", "all"])
    assert (args.segment, args.waymo_cameras) == (SEGMENT, "all")
    args = build_parser().parse_args(["run", "--data", "d", "--out", "o"])
    assert (args.segment, args.waymo_cameras) == (None, "front3")
