"""EuRoC and TUM RGB-D readers on tiny fixture folders written here."""

import cv2
import numpy as np
import pytest

from mcgs_warp.data import open_sequence
from mcgs_warp.data.euroc import EurocSequence
from mcgs_warp.data.tum import TumSequence, associate
from mcgs_warp.errors import InputError

T_BS = [
    [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
    [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
    [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
    [0.0, 0.0, 0.0, 1.0],
]

SENSOR = """%YAML:1.0
---
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)
T_BS:
  cols: 4
  rows: 4
  data: [{data}]
rate_hz: 20
resolution: [{w}, {h}]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


def make_euroc(root, w=40, h=30, stamps=(1403636579763555584, 1403636579813555456, 1403636579863555584), cam1_shift_ns=0):
    rng = np.random.default_rng(0)
    for i in (0, 1):
        cam = root / "mav0" / f"cam{i}"
        (cam / "data").mkdir(parents=True)
        data = ", ".join(f"{v!r}" for row in T_BS for v in row)
        (cam / "sensor.yaml").write_text(SENSOR.format(data=data, w=w, h=h))
        lines = ["#timestamp [ns],filename"]
        for ns in stamps if i == 0 else [v + cam1_shift_ns for v in stamps[1:]]:  # cam1 misses the first frame
            cv2.imwrite(str(cam / "data" / f"{ns}.png"), rng.integers(0, 255, (h, w), dtype=np.uint8))
            lines.append(f"{ns},{ns}.png")
        (cam / "data.csv").write_text("\n".join(lines) + "\n")
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir(parents=True)
    (gt / "data.csv").write_text(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []\n"
        f"{stamps[0]},4.688,-1.786,0.783,0.534,-0.153,-0.827,-0.082\n"
        f"{stamps[1]},4.689,-1.787,0.784,0.534,-0.153,-0.827,-0.082\n"
    )
    return root


def test_euroc_reader(tmp_path):
    root = make_euroc(tmp_path / "MH_01_easy")
    seq = open_sequence(root)
    assert isinstance(seq, EurocSequence)
    assert len(seq.rig) == 2 and len(seq) == 2  # only timestamps both cameras have
    cam = seq.rig.cameras[0]
    assert cam.model == "pinhole" and cam.intrinsics == (458.654, 457.296, 367.215, 248.375)
    assert cam.distortion[0] == pytest.approx(-0.28340811)
    np.testing.assert_allclose(cam.T_b_c, T_BS, atol=1e-12)
    np.testing.assert_allclose(seq.timestamps[0], 1403636579.813555456, atol=1e-6)
    f = seq[0]
    assert f.images[0].shape == (30, 40, 3) and np.allclose(f.images[0][..., 0], f.images[0][..., 2])
    # ground truth quaternion (w, x, y, z) -> rotation
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat([-0.153, -0.827, -0.082, 0.534]).as_matrix()
    np.testing.assert_allclose(seq.groundtruth.poses[0, :3, :3], R, atol=1e-9)
    np.testing.assert_allclose(seq.groundtruth.positions[1], [4.689, -1.787, 0.784])


def test_euroc_pairs_cameras_within_a_sync_tolerance(tmp_path):
    """A software-synced recording: cam1's stamps 1.5 ms after cam0's still pair (nearest
    first, the frame stamped with cam0's time); 8 ms apart they do not (MAX_SYNC_DT 5 ms)."""
    seq = open_sequence(make_euroc(tmp_path / "a", cam1_shift_ns=1_500_000))
    assert len(seq) == 2
    np.testing.assert_allclose(seq.timestamps[0], 1403636579.813555456, atol=1e-6)
    assert seq._ns[0] == (1403636579813555456, 1403636579813555456 + 1_500_000)
    assert seq[1].images[1].shape == (30, 40, 3)
    with pytest.raises(InputError, match="no images within 5 ms"):
        open_sequence(make_euroc(tmp_path / "b", cam1_shift_ns=8_000_000))


def test_euroc_errors(tmp_path):
    root = make_euroc(tmp_path / "seq")
    sensor = root / "mav0" / "cam1" / "sensor.yaml"
    text = sensor.read_text()
    sensor.write_text(text.replace("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [458.654, 457.296]"))
    with pytest.raises(InputError, match=r"cam1/sensor.yaml: intrinsics: expected 4 numbers, got 2"):
        open_sequence(root)
    sensor.write_text(text.replace("data: [", "data: [1.0, "))
    with pytest.raises(InputError, match=r"cam1/sensor.yaml: T_BS.data: expected 16 numbers, got 17"):
        open_sequence(root)
    sensor.write_text(text)
    (root / "mav0" / "cam0" / "data.csv").write_text("#timestamp [ns],filename\nabc,1.png\n")
    with pytest.raises(InputError, match=r"cam0/data.csv: line 2: expected an integer timestamp"):
        open_sequence(root)


def make_tum(root, n=4):
    rng = np.random.default_rng(1)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, dep = ["# color images"], ["# depth maps"]
    depths = []
    for k in range(n):
        t = 1305031102.175304 + 0.033 * k
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), rng.integers(0, 255, (480, 640, 3), dtype=np.uint8))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        if k != 2:  # frame 2 has no depth within 20 ms
            td = t + 0.004
            d = rng.integers(1000, 20000, (480, 640)).astype(np.uint16)
            cv2.imwrite(str(root / "depth" / f"{td:.6f}.png"), d)
            dep.append(f"{td:.6f} depth/{td:.6f}.png")
            depths.append(d)
        else:
            depths.append(None)
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(dep) + "\n")
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n1305031102.1758 1.3405 0.6266 1.6575 0.6574 0.6126 -0.2949 -0.3248\n")
    return depths


def test_tum_reader(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    depths = make_tum(root)
    seq = open_sequence(root)
    assert isinstance(seq, TumSequence) and len(seq) == 4
    assert seq.rig.cameras[0].intrinsics == (517.3, 516.5, 318.6, 255.3)
    f = seq[1]
    np.testing.assert_allclose(f.depths[0], depths[1] / 5000.0, rtol=1e-6)
    # a frame without depth within 20 ms is a dropout (no depth pixel), not a mode switch
    assert seq.depth_cameras() == [True] and seq[2].depths[0].shape == (480, 640) and not seq[2].depths[0].any()
    assert len(seq.groundtruth) == 1


def test_tum_depth_mode_does_not_depend_on_the_first_frame(tmp_path, capsys):
    """Depth missing on frame 0 only: the sequence still has depth (frame 0 has none of its
    pixels); depth.txt matching no frame at all: no depth, said once."""
    root = tmp_path / "rgbd_dataset_freiburg1_a"
    make_tum(root)
    lines = (root / "depth.txt").read_text().splitlines()
    (root / "depth.txt").write_text("\n".join(lines[:1] + lines[2:]) + "\n")  # frame 0's depth gone
    seq = open_sequence(root)
    assert seq.depth_cameras() == [True] and not seq[0].depths[0].any() and seq[1].depths[0].any()
    (root / "depth.txt").write_text("# depth maps\n1.0 depth/none.png\n")
    seq = open_sequence(root)
    assert seq.depth_cameras() == [False] and seq[0].depths[0] is None
    assert "no rgb frame (rgb.txt) has a depth frame" in capsys.readouterr().err


def test_tum_time_offset_moves_frames_onto_the_rig_clock(tmp_path):
    """rig.yaml time_offset (camera clock = rig clock + offset): frame stamps minus the offset,
    depth still associated on the sensor's own clock."""
    from mcgs_warp.rig import CameraSpec, Rig, save_rig

    root = tmp_path / "seq"
    make_tum(root)
    save_rig(Rig([CameraSpec("rgb", "pinhole", 640, 480, (517.3, 516.5, 318.6, 255.3), time_offset=0.25)]), root / "rig.yaml")
    seq = open_sequence(root)  # a TUM folder with its own rig.yaml is still TUM
    assert isinstance(seq, TumSequence)
    np.testing.assert_allclose(seq.timestamps[0], 1305031102.175304 - 0.25, atol=1e-6)
    assert seq[1].depths[0].any()


def test_tum_needs_a_calibration(tmp_path):
    root = tmp_path / "my_sequence"
    make_tum(root, n=2)
    with pytest.raises(InputError, match="missing calibration"):
        open_sequence(root)


def test_associate_nearest_within_tolerance():
    a = np.array([0.0, 0.1, 0.2, 0.3])
    b = np.array([0.005, 0.118, 0.26, 0.31])
    assert associate(a, b).tolist() == [0, 1, -1, 3]


def test_a_rig_given_for_a_euroc_folder_replaces_its_calibration(tmp_path, capsys):
    """`run --rig` / `--from-kalibr` on a EuRoC folder: the given rig's calibration replaces
    sensor.yaml's, and its time offsets pair the images (a Kalibr timeshift of 8 ms brings
    cam1's late stamps back within the 5 ms tolerance); one whose body is not the folder's
    (where ground truth exists) is warned about; a rig of another shape is refused."""
    import copy

    root = make_euroc(tmp_path / "seq", cam1_shift_ns=8_000_000)
    with pytest.raises(InputError, match="no images within 5 ms"):
        open_sequence(root)
    rig = copy.deepcopy(EurocSequence(make_euroc(tmp_path / "ref")).rig)
    rig.cameras[1].time_offset = 0.008  # cam1's clock = rig clock + 8 ms
    rig.cameras[1].intrinsics = (450.0, 450.0, 20.0, 15.0)
    seq = open_sequence(root, rig=rig, rig_source="kalibr.yaml")
    assert len(seq) == 2 and seq.rig.cameras[1].intrinsics == (450.0, 450.0, 20.0, 15.0)
    assert "camera 0 sits" not in capsys.readouterr().err  # same body
    cam0_body = copy.deepcopy(rig)  # a camera-only camchain: the body is cam0, not EuRoC's IMU
    T_c0_b = np.linalg.inv(rig.cameras[0].T_b_c)
    for c in cam0_body.cameras:
        c.T_b_c = T_c0_b @ c.T_b_c
    open_sequence(root, rig=cam0_body, rig_source="kalibr.yaml")
    err = capsys.readouterr().err
    assert "kalibr.yaml: camera 0 sits 6.9 cm and" in err and "ATE compares different frames" in err, err
    small = copy.deepcopy(rig)
    small.cameras[0].width = 20
    with pytest.raises(InputError, match=r"kalibr.yaml: cameras\[0\].resolution: expected 40x30"):
        open_sequence(make_euroc(tmp_path / "c"), rig=small, rig_source="kalibr.yaml")
