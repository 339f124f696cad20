"""nuScenes reader on fixture folders written here in the devkit's layout (docs/schema_nuscenes.md),
with known calibration and constant ego motion, so the cost of grouping the unsynchronized cameras
into rig frames is known exactly."""

import json

import cv2
import numpy as np
import pytest

from mcgs_warp.data import open_sequence
from mcgs_warp.data.nuscenes import CHANNELS, NuScenesSequence, is_nuscenes, nuscenes_scenes
from mcgs_warp.errors import InputError
from mcgs_warp.geometry import invert

T0 = 1531883530412470  # us
W, H = 64, 48
SPEED = 10.0  # m/s, constant, straight along the heading
HEADING = 0.4  # rad
# each camera fires this long after CAM_FRONT within a sweep (us): 40 ms spread, as the lidar sweeps past
OFFSET = {"CAM_FRONT": 0, "CAM_FRONT_RIGHT": 8000, "CAM_BACK_RIGHT": 16000, "CAM_BACK": 24000, "CAM_BACK_LEFT": 32000, "CAM_FRONT_LEFT": 40000}
YAW = {"CAM_FRONT": 0.0, "CAM_FRONT_RIGHT": -0.96, "CAM_BACK_RIGHT": -1.92, "CAM_BACK": np.pi, "CAM_BACK_LEFT": 1.92, "CAM_FRONT_LEFT": 0.96}
SWEEP_US = 83_333  # cameras at 12 Hz
Q_CAM_TO_EGO = (0.5, -0.5, 0.5, -0.5)  # (w, x, y, z): camera z (forward) -> ego x, camera x (right) -> ego -y


# the devkit's conventions, written out here (pyquaternion, Hamilton, (w, x, y, z))
def qmul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


def qrot(q, v):
    w, x, y, z = qmul(qmul(q, (0.0, *v)), (q[0], -q[1], -q[2], -q[3]))
    return np.array([x, y, z])


def q_yaw(a):
    return (np.cos(a / 2), 0.0, 0.0, np.sin(a / 2))


def calibrated(channel):
    """translation (m), rotation (w, x, y, z), intrinsic 3x3 of a camera: sensor -> ego."""
    i = CHANNELS.index(channel)
    q = qmul(q_yaw(YAW[channel]), qmul(Q_CAM_TO_EGO, (np.cos(0.01 * i), np.sin(0.01 * i), 0.0, 0.0)))  # a little roll about the optical axis
    t = [1.5 * np.cos(YAW[channel]) + 0.1 * i, 0.8 * np.sin(YAW[channel]), 1.5 + 0.01 * i]
    K = [[40.0 + i, 0.0, 31.5 + 0.1 * i], [0.0, 41.0 + i, 23.5 - 0.1 * i], [0.0, 0.0, 1.0]]
    return t, list(q), K


def ego(t_us):
    """Ego pose at time t (us): translation, rotation (w, x, y, z)."""
    dt = (t_us - T0) * 1e-6
    return [300.0 + SPEED * dt * np.cos(HEADING), 1200.0 + SPEED * dt * np.sin(HEADING), 0.0], list(q_yaw(HEADING))


def devkit_project(X_w, ego_rec, cs_rec):
    """Global -> ego -> camera -> pixels, as nuscenes.py map_pointcloud_to_image and view_points do."""
    t, q = ego_rec
    p = qrot((q[0], -q[1], -q[2], -q[3]), X_w - np.array(t))
    t, q, K = cs_rec
    p = qrot((q[0], -q[1], -q[2], -q[3]), p - np.array(t))
    uvw = np.array(K) @ p
    return uvw[:2] / uvw[2]


def make_nuscenes(root, scenes=("scene-0061",), n=4, version="v1.0-mini", sweeps=True):
    tables = root / version
    tables.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    sensor = [{"token": f"sensor-{c}", "channel": c, "modality": "camera"} for c in CHANNELS] + [{"token": "sensor-lidar", "channel": "LIDAR_TOP", "modality": "lidar"}]
    cs = [{"token": f"cs-{c}", "sensor_token": f"sensor-{c}", **dict(zip(("translation", "rotation", "camera_intrinsic"), calibrated(c)))} for c in CHANNELS]
    cs.append({"token": "cs-lidar", "sensor_token": "sensor-lidar", "translation": [0.9, 0.0, 1.8], "rotation": [1.0, 0, 0, 0], "camera_intrinsic": []})
    scene, sample, sample_data, ego_pose = [], [], [], []
    for si, name in enumerate(scenes):
        t_scene = T0 + si * 30_000_000
        tokens = [f"{name}-sample-{s}" for s in range(n)]
        for s, tok in enumerate(tokens):
            sample.append({"token": tok, "timestamp": t_scene + 500_000 * s, "prev": tokens[s - 1] if s else "", "next": tokens[s + 1] if s + 1 < n else "", "scene_token": f"{name}-token"})
        scene.append({"token": f"{name}-token", "log_token": "log-0", "nbr_samples": n, "first_sample_token": tokens[0], "last_sample_token": tokens[-1], "name": name, "description": "fixture"})
        for s in range(n):
            for j in range(6 if sweeps and s + 1 < n else 1):  # keyframe, then the sweeps up to the next sample
                for c in CHANNELS + ("LIDAR_TOP",):
                    t = t_scene + 500_000 * s + SWEEP_US * j + OFFSET.get(c, 20000)
                    key = j == 0
                    folder = "samples" if key else "sweeps"
                    tok = f"{name}-{c}-{s}-{j}"
                    fname = f"{folder}/{c}/{name}__{c}__{t}.{'jpg' if c != 'LIDAR_TOP' else 'pcd.bin'}"
                    ego_pose.append({"token": f"ego-{tok}", "timestamp": t, **dict(zip(("translation", "rotation"), ego(t)))})
                    sample_data.append({"token": tok, "sample_token": f"{name}-sample-{s if key else s + 1}", "ego_pose_token": f"ego-{tok}",
                                        "calibrated_sensor_token": f"cs-{c}" if c != "LIDAR_TOP" else "cs-lidar", "timestamp": t,
                                        "fileformat": "jpg" if c != "LIDAR_TOP" else "pcd", "is_key_frame": key,
                                        "height": H if c != "LIDAR_TOP" else 0, "width": W if c != "LIDAR_TOP" else 0, "filename": fname, "prev": "", "next": ""})
                    if c != "LIDAR_TOP":
                        (root / folder / c).mkdir(parents=True, exist_ok=True)
                        cv2.imwrite(str(root / fname), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
    log = [{"token": "log-0", "logfile": "n015-2018-07-18-11-07-57+0800", "vehicle": "n015", "date_captured": "2018-07-18", "location": "singapore-onenorth"}]
    for name, rows in (("sensor", sensor), ("calibrated_sensor", cs), ("scene", scene), ("sample", sample), ("sample_data", sample_data), ("ego_pose", ego_pose), ("log", log)):
        (tables / f"{name}.json").write_text(json.dumps(rows, indent=0))
    return root


def test_keyframes_rig_poses_images_and_projection(tmp_path, capsys):
    root = make_nuscenes(tmp_path / "nuscenes")
    assert is_nuscenes(root)
    seq = open_sequence(root)
    assert isinstance(seq, NuScenesSequence) and seq.name == "scene-0061" and len(seq) == 4 and seq.version == "v1.0-mini"
    assert [c.name for c in seq.rig.cameras] == list(CHANNELS)
    t_front = T0 + 500_000 * np.arange(4)
    np.testing.assert_allclose(seq.timestamps, t_front * 1e-6, rtol=0, atol=1e-9)
    for k in range(4):  # ground truth: CAM_FRONT's ego pose, exactly
        t, q = ego(t_front[k])
        np.testing.assert_allclose(seq.groundtruth.poses[k][:3, 3], t, rtol=0, atol=1e-9)
        np.testing.assert_allclose(seq.groundtruth.poses[k][:3, :3] @ [1.0, 2.0, 3.0], qrot(q, [1.0, 2.0, 3.0]), rtol=0, atol=1e-9)
    for spec in seq.rig.cameras:
        t, q, K = calibrated(spec.name)
        assert spec.model == "pinhole" and spec.distortion == () and (spec.width, spec.height) == (W, H)
        assert spec.intrinsics == (K[0][0], K[1][1], K[0][2], K[1][2])
        np.testing.assert_allclose(spec.T_b_c[:3, 3], t, rtol=0, atol=1e-12)
        np.testing.assert_allclose(spec.T_b_c[:3, :3] @ [0.3, -1.0, 2.0], qrot(q, [0.3, -1.0, 2.0]), rtol=0, atol=1e-12)
    # a world point before each camera lands on the same pixel in the devkit's chain and through our rig
    for k in (0, 3):
        for c, spec in enumerate(seq.rig.cameras):
            T_w_c = seq.image_poses[k, c] @ spec.T_b_c
            X_w = (T_w_c @ [0.5, -0.4, 7.0, 1.0])[:3]
            want = devkit_project(X_w, ego(t_front[k] + OFFSET[spec.name]), calibrated(spec.name))
            assert 0 < want[0] < W and 0 < want[1] < H
            x = invert(T_w_c) @ np.append(X_w, 1.0)
            fx, fy, cx, cy = spec.intrinsics
            np.testing.assert_allclose([fx * x[0] / x[2] + cx, fy * x[1] / x[2] + cy], want, rtol=0, atol=1e-3)
    f = seq[2]
    assert f.index == 2 and f.depths == [None] * 6 and f.timestamp == seq.timestamps[2]
    raw = cv2.imread(str(root / "samples" / "CAM_BACK" / f"scene-0061__CAM_BACK__{t_front[2] + OFFSET['CAM_BACK']}.jpg"))[..., ::-1] / np.float32(255)
    assert f.images[4].dtype == np.float32 and f.images[4].shape == (H, W, 3)
    np.testing.assert_array_equal(f.images[4], raw)


def test_time_grouping_cost_at_constant_motion(tmp_path, capsys):
    """The rig frame's pose is CAM_FRONT's; a camera that fired dt later sits SPEED * dt further
    along: 10 m/s x 40 ms = 0.4 m for CAM_FRONT_LEFT. The reader measures exactly that."""
    seq = NuScenesSequence(make_nuscenes(tmp_path / "n"), sweeps=True)
    assert len(seq) == 4 + 3 * 5  # every CAM_FRONT image: 4 keyframes and 5 sweeps between each pair
    dt = seq.image_timestamps - seq.timestamps[:, None]  # [K, C] s
    np.testing.assert_allclose(dt, np.broadcast_to([OFFSET[c] * 1e-6 for c in CHANNELS], dt.shape), atol=1e-6)
    for k in range(len(seq)):
        for c, spec in enumerate(seq.rig.cameras):
            rig_pose = seq.groundtruth.poses[k] @ spec.T_b_c  # where the rig model puts camera c
            own_pose = seq.image_poses[k, c] @ spec.T_b_c  # where it was when it fired
            np.testing.assert_allclose(np.linalg.norm(rig_pose[:3, 3] - own_pose[:3, 3]), SPEED * abs(OFFSET[spec.name]) * 1e-6, rtol=0, atol=1e-9)
    np.testing.assert_allclose(seq.sync_error, SPEED * 0.040, rtol=0, atol=1e-9)
    err = capsys.readouterr().err
    assert "up to 40 ms apart" in err and "misplaces the others by up to 0.40 m" in err
    # sweeps' frames are the CAM_FRONT sweeps; keyframes are among them
    keys = NuScenesSequence(tmp_path / "n")
    assert np.isin(keys.timestamps, seq.timestamps).all()
    np.testing.assert_array_equal(keys.image_poses, seq.image_poses[::6])


def test_scene_and_version_choice(tmp_path):
    root = make_nuscenes(tmp_path / "n", scenes=("scene-0061", "scene-0103"), sweeps=False)
    with pytest.raises(InputError, match=r"holds 2 scenes: choose one with --segment NAME \(scene-0061, scene-0103\)"):
        open_sequence(root)
    seq = open_sequence(root, segment="scene-0103")
    assert seq.name == "scene-0103" and seq.timestamps[0] == (T0 + 30_000_000) * 1e-6
    with pytest.raises(InputError, match="scene-9999: no such scene; scenes: scene-0061, scene-0103"):
        open_sequence(root, segment="scene-9999")
    make_nuscenes(root, scenes=("scene-0077",), version="v1.0-test", sweeps=False)
    assert NuScenesSequence(root, "scene-0077").version == "v1.0-test"  # the scene picks its version
    with pytest.raises(InputError, match="expected one v1.0-\\* table folder, found v1.0-mini, v1.0-test"):
        NuScenesSequence(root)
    # a named scene in none, or in two, of the table folders: said as such (not "name the scene")
    with pytest.raises(InputError, match="scene-9999: no such scene in v1.0-mini, v1.0-test$"):
        NuScenesSequence(root, "scene-9999")
    make_nuscenes(root, scenes=("scene-0061",), version="v1.0-trainval", sweeps=False)
    with pytest.raises(InputError, match=r"scene-0061: the scene is in 2 table folders \(v1.0-mini, v1.0-trainval\); expected one"):
        NuScenesSequence(root, "scene-0061")
    assert nuscenes_scenes(root) == ["scene-0061", "scene-0077", "scene-0103"]  # each once, over the table folders


def test_bad_nuscenes_folders(tmp_path):
    root = make_nuscenes(tmp_path / "n", sweeps=False)
    tables = root / "v1.0-mini"
    # a missing table
    poses = (tables / "ego_pose.json").read_text()
    (tables / "ego_pose.json").unlink()
    with pytest.raises(InputError, match=r"ego_pose.json: missing table"):
        NuScenesSequence(root)
    # a truncated table
    (tables / "ego_pose.json").write_text(poses[: len(poses) // 2])
    with pytest.raises(InputError, match=r"ego_pose.json: line \d+, column \d+: not valid JSON \(truncated\?\)"):
        NuScenesSequence(root)
    (tables / "ego_pose.json").write_text(poses)
    # an unknown camera
    sensors = json.loads((tables / "sensor.json").read_text())
    (tables / "sensor.json").write_text(json.dumps([dict(sensors[0], channel="CAM_ROOF")] + sensors[1:]))
    with pytest.raises(InputError, match="unknown camera 'CAM_ROOF': expected one of CAM_FRONT_LEFT, CAM_FRONT"):
        NuScenesSequence(root)
    (tables / "sensor.json").write_text(json.dumps(sensors))
    # a missing field, a missing image
    rows = json.loads((tables / "sample_data.json").read_text())
    (tables / "sample_data.json").write_text(json.dumps([{k: v for k, v in rows[0].items() if k != "ego_pose_token"}] + rows[1:]))
    with pytest.raises(InputError, match=r"sample_data.json: \[0\]: missing field ego_pose_token"):
        NuScenesSequence(root)
    (tables / "sample_data.json").write_text(json.dumps(rows))
    (root / rows[0]["filename"]).unlink()
    with pytest.raises(InputError, match=r"image file is missing \(1 of the scene's 24 images are\)"):
        NuScenesSequence(root)
