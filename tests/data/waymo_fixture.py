"""A tiny Waymo Open Dataset v2 folder (Parquet, the release's column names and types:
src/waymo_open_dataset/v2/perception/{base,camera_image,context,pose}.py) with known
calibration, poses and images, for tests/data/test_waymo.py and tests/system/test_batch.py.
Needs pyarrow (imported when a folder is written)."""

import cv2
import numpy as np

from mcgs_warp.geometry import yaw_pitch_roll

SEGMENT = "10023947602400723454_1120_000_1140_000"
T0 = 1552440195362591  # us
NAMES = {1: "FRONT", 2: "FRONT_LEFT", 3: "FRONT_RIGHT", 4: "SIDE_LEFT", 5: "SIDE_RIGHT"}
W, H, H_SIDE = 64, 48, 32
CAL = "[CameraCalibrationComponent]"


def calibration(cam: int):
    """Known intrinsics (f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3) and extrinsic (Waymo camera -> vehicle)."""
    intr = (50.0 + cam, 51.0 + cam, 31.5 + 0.1 * cam, (H if cam < 4 else H_SIDE) / 2 - 0.3, -0.05 * cam, 0.01, 1e-3, -2e-3, 1e-3)
    yaw = {1: 0.0, 2: 0.8, 3: -0.8, 4: 1.6, 5: -1.6}[cam]
    E = np.eye(4)
    E[:3, :3] = yaw_pitch_roll(yaw, 0.02 * cam, -0.01 * cam)
    E[:3, 3] = [1.5 + 0.1 * cam, 0.2 * np.sin(yaw), 2.0]
    return intr, E


def vehicle_pose(k: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = yaw_pitch_roll(0.3 + 0.05 * k, 0.01, -0.02)
    T[:3, 3] = [860.5 + 1.1 * k, 15568.6 - 0.3 * k, -651.4]
    return T


def image(k: int, cam: int) -> bytes:
    rng = np.random.default_rng(10 * k + cam)
    ok, buf = cv2.imencode(".jpg", rng.integers(0, 255, (H if cam < 4 else H_SIDE, W, 3), dtype=np.uint8))
    return buf.tobytes()


def make_waymo(root, segment=SEGMENT, n=4, cameras=(1, 2, 3, 4, 5), row_group_size=3):
    """Write segment ``segment`` (``n`` frames, 100 ms apart, of ``cameras``) under ``root``; returns ``root``."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    TRANSFORM = pa.list_(pa.float64(), 16)
    for comp in ("camera_image", "camera_calibration", "vehicle_pose"):
        (root / comp).mkdir(parents=True, exist_ok=True)
    rows = [(T0 + 100_000 * k, cam) for k in range(n) for cam in cameras]
    pq.write_table(pa.table({
        "key.segment_context_name": pa.array([segment] * len(rows), pa.string()),
        "key.frame_timestamp_micros": pa.array([t for t, _ in rows], pa.int64()),
        "key.camera_name": pa.array([c for _, c in rows], pa.int8()),
        "[CameraImageComponent].image": pa.array([image((t - T0) // 100_000, c) for t, c in rows], pa.binary()),
        "[CameraImageComponent].pose.transform": pa.array([vehicle_pose((t - T0) // 100_000).ravel().tolist() for t, _ in rows], TRANSFORM),
        "[CameraImageComponent].pose_timestamp": pa.array([t * 1e-6 + 0.01 * c for t, c in rows], pa.float64()),
    }), root / "camera_image" / f"{segment}.parquet", row_group_size=row_group_size)
    cal = {k: [] for k in ("f_u", "f_v", "c_u", "c_v", "k1", "k2", "p1", "p2", "k3")}
    for cam in cameras:
        for key, v in zip(cal, calibration(cam)[0]):
            cal[key].append(v)
    pq.write_table(pa.table({
        "key.segment_context_name": pa.array([segment] * len(cameras), pa.string()),
        "key.camera_name": pa.array(list(cameras), pa.int8()),
        **{f"{CAL}.intrinsic.{k}": pa.array(v, pa.float64()) for k, v in cal.items()},
        f"{CAL}.extrinsic.transform": pa.array([calibration(c)[1].ravel().tolist() for c in cameras], TRANSFORM),
        f"{CAL}.width": pa.array([W] * len(cameras), pa.int32()),
        f"{CAL}.height": pa.array([H if c < 4 else H_SIDE for c in cameras], pa.int32()),
        f"{CAL}.rolling_shutter_direction": pa.array([2] * len(cameras), pa.int8()),
    }), root / "camera_calibration" / f"{segment}.parquet")
    pq.write_table(pa.table({
        "key.segment_context_name": pa.array([segment] * n, pa.string()),
        "key.frame_timestamp_micros": pa.array([T0 + 100_000 * k for k in range(n)], pa.int64()),
        "[VehiclePoseComponent].world_from_vehicle.transform": pa.array([vehicle_pose(k).ravel().tolist() for k in range(n)], TRANSFORM),
    }), root / "vehicle_pose" / f"{segment}.parquet")
    return root
