"""Write a sequence of our folder format in the layouts of public datasets (EuRoC MAV,
KITTI odometry, TUM RGB-D), as their tools do, so that the readers can be run end to end on
the built-in synthetic sequence."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mcgs_warp.geometry import matrix_to_quat
from mcgs_warp.rig import CameraSpec, Rig, save_rig

EUROC_T0_NS = 1403636579763555584  # a EuRoC-like clock: nanoseconds


def stereo_rig(baseline: float = 0.3) -> Rig:
    """Two forward pinhole cameras without distortion, ``baseline`` m apart along the body's
    y axis (body x forward, y left, z up): rectified, as KITTI needs."""
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical -> body
    cams = []
    for name, y in (("left", baseline / 2), ("right", -baseline / 2)):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, [0.25, y, 0.0]
        cams.append(CameraSpec(name, "pinhole", 320, 240, (180.0, 180.0, 159.5, 119.5), (), T))
    return Rig(cams)


def _grey(img) -> np.ndarray:
    return cv2.cvtColor((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def write_euroc(seq, root) -> Path:
    """EuRoC MAV layout (``mav0/cam0``, ``cam1``, ``state_groundtruth_estimate0``): grey
    images named by nanosecond stamps, ``sensor.yaml`` with ``T_BS`` (camera -> body)."""
    mav = Path(root) / "mav0"
    ns = [EUROC_T0_NS + int(round(t * 1e9)) for t in seq.timestamps - seq.timestamps[0]]
    for i, cam in enumerate(seq.rig.cameras):
        folder = mav / f"cam{i}"
        (folder / "data").mkdir(parents=True)
        lines = ["#timestamp [ns],filename"]
        for k, stamp in enumerate(ns):
            cv2.imwrite(str(folder / "data" / f"{stamp}.png"), _grey(seq[k].images[i]))
            lines.append(f"{stamp},{stamp}.png")
        (folder / "data.csv").write_text("\n".join(lines) + "\n")
        data = ", ".join(repr(float(v)) for v in cam.T_b_c.ravel())
        dist = list(cam.distortion) + [0.0] * (4 - len(cam.distortion))
        (folder / "sensor.yaml").write_text(
            "%YAML:1.0\n---\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n"
            f"  data: [{data}]\nrate_hz: 10\nresolution: [{cam.width}, {cam.height}]\ncamera_model: pinhole\n"
            f"intrinsics: {list(cam.intrinsics)}\ndistortion_model: radial-tangential\ndistortion_coefficients: {dist[:4]}\n"
        )
    gt = mav / "state_groundtruth_estimate0"
    gt.mkdir(parents=True)
    q = matrix_to_quat(seq.groundtruth.poses[:, :3, :3])  # x y z w
    rows = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
    for stamp, T, qq in zip(ns, seq.groundtruth.poses, q):
        rows.append(",".join([str(stamp), *(repr(float(v)) for v in T[:3, 3]), *(repr(float(v)) for v in (qq[3], qq[0], qq[1], qq[2]))]))
    (gt / "data.csv").write_text("\n".join(rows) + "\n")
    return Path(root)


def write_kitti(seq, root) -> Path:
    """KITTI odometry layout (``image_0``, ``image_1``, ``calib.txt``, ``times.txt``,
    ``poses.txt``) of a rectified two-camera rig: ``P_i = K [I | t_i]`` with camera 0 the body,
    poses ``T_w_cam0`` relative to the first frame."""
    root = Path(root)
    c0, c1 = seq.rig.cameras
    fx, fy, cx, cy = c0.intrinsics
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    lines = []
    for i, cam in enumerate((c0, c1, c0, c1)):
        t = (np.linalg.inv(cam.T_b_c) @ c0.T_b_c)[:3, 3]  # camera 0's origin in camera i's frame
        P = K @ np.hstack([np.eye(3), t[:, None]])
        lines.append(f"P{i}: " + " ".join(f"{v:.12e}" for v in P.ravel()))
    (root).mkdir(parents=True, exist_ok=True)
    (root / "calib.txt").write_text("\n".join(lines) + "\n")
    for i in (0, 1):
        (root / f"image_{i}").mkdir()
        for k in range(len(seq)):
            cv2.imwrite(str(root / f"image_{i}" / f"{k:06d}.png"), _grey(seq[k].images[i]))
    (root / "times.txt").write_text("".join(f"{t - seq.timestamps[0]:.6e}\n" for t in seq.timestamps))
    T_w_c0 = seq.groundtruth.poses @ c0.T_b_c
    rel = np.linalg.inv(T_w_c0[0]) @ T_w_c0
    (root / "poses.txt").write_text("".join(" ".join(f"{v:.12e}" for v in T[:3].ravel()) + "\n" for T in rel))
    return root


def write_tum(seq, root, camera: int = 0) -> Path:
    """TUM RGB-D layout of one camera: ``rgb/``, ``depth/`` (16-bit, 5000 per metre, from the
    sequence's exact depth; 0 beyond the 13.1 m the format holds), ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` (camera poses) and a
    ``rig.yaml`` with that camera alone (``T_b_c = I``: TUM's poses are the camera's)."""
    from mcgs_warp.data.trajectory import Trajectory, write_tum as write_trajectory

    root = Path(root)
    cam = seq.rig.cameras[camera]
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    t0 = 1305031102.175304
    rgb, dep = ["# color images"], ["# depth maps"]
    for k in range(len(seq)):
        t = t0 + seq.timestamps[k] - seq.timestamps[0]
        f = seq[k]
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), (np.clip(f.images[camera], 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1])
        exact = seq.gt_depths(k)[camera]
        units = np.round(exact * 5000)
        cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), np.where(units <= 65535, units, 0).astype(np.uint16))  # beyond 13.1 m: none, as a sensor
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        dep.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(dep) + "\n")
    stamps = t0 + seq.timestamps - seq.timestamps[0]
    write_trajectory(root / "groundtruth.txt", Trajectory(stamps, seq.groundtruth.poses @ cam.T_b_c))
    save_rig(Rig([CameraSpec(cam.name, cam.model, cam.width, cam.height, cam.intrinsics, cam.distortion)]), root / "rig.yaml")
    return root
