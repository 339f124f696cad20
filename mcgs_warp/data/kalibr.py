"""Kalibr calibrations (``camchain.yaml``, ``camchain-imucam.yaml``) read as a :class:`Rig`.

Kalibr writes one block per camera, ``cam0``, ``cam1``, ...::

    cam1:
      camera_model: pinhole            # pinhole | omni | ds | eucm
      intrinsics: [fu, fv, pu, pv]     # pixels (omni: [xi, fu, fv, pu, pv]; ds, eucm: 6 numbers)
      distortion_model: radtan         # radtan | equidistant | fov | none
      distortion_coeffs: [k1, k2, r1, r2]
      resolution: [752, 480]
      T_cn_cnm1: 4x4                   # camera n-1 -> camera n (point in cam n-1 -> cam n)
      T_cam_imu: 4x4                   # IMU -> camera (camchain-imucam.yaml only)
      timeshift_cam_imu: 0.0           # s, t_imu = t_cam + timeshift
      rostopic: /cam1/image_raw

The rig's body is the IMU when ``cam0`` has ``T_cam_imu`` (then ``T_b_c = T_cam_imu^-1``;
a camera without it is chained to its predecessor by ``T_cn_cnm1``), else camera 0 (``T_b_c``
the inverse of the product of ``T_cn_cnm1`` down the chain). ``timeshift_cam_imu`` becomes
``time_offset = -timeshift`` (our camera clock = rig clock + offset). Models map onto ours:
``pinhole-radtan`` and ``pinhole-none`` -> ``pinhole`` (OpenCV's k1, k2, p1, p2),
``pinhole-equi`` -> ``fisheye`` (OpenCV's fisheye k1..k4); ``omni``, ``ds``, ``eucm`` and ``fov``
are refused by name. Matrices may be 4 rows of 4 numbers (as Kalibr writes them) or 16 numbers.
"""

from __future__ import annotations

import re

import numpy as np

from ..errors import InputError, warn
from ..geometry import invert, pose_distance
from ..rig import CameraSpec, Rig, load_yaml, parse_camera, parse_pose, rig_from_dict

#: (camera_model, distortion_model) -> our model
MODELS = {("pinhole", "radtan"): "pinhole", ("pinhole", "none"): "pinhole", ("pinhole", "equidistant"): "fisheye"}
CHAIN_TOLERANCE = (1e-3, np.radians(0.05))  # m, rad: T_cam_imu and T_cn_cnm1 that disagree more are worth a word


def _camera_names(src, data) -> list[str]:
    if not isinstance(data, dict):
        raise InputError(src, None, f"expected a Kalibr camchain (a mapping with cam0, cam1, ...), got {type(data).__name__}")
    names = sorted((k for k in data if re.fullmatch(r"cam\d+", str(k))), key=lambda k: int(k[3:]))
    if not names:
        raise InputError(src, None, "no cam0, cam1, ... blocks: not a Kalibr camchain")
    for i, n in enumerate(names):
        if n != f"cam{i}":
            raise InputError(src, f"cam{i}", f"missing camera block (Kalibr numbers cameras cam0..cam{len(names) - 1} without gaps; found {', '.join(names)})")
    return names


def _model(src, name, d) -> str:
    cm, dm = d.get("camera_model"), d.get("distortion_model", "none")
    if cm is None:
        raise InputError(src, f"{name}.camera_model", "missing field")
    for key, v in (("camera_model", cm), ("distortion_model", dm)):
        if not isinstance(v, str):
            raise InputError(src, f"{name}.{key}", f"expected a model name, got {v!r}")
    if (cm, dm) not in MODELS:
        supported = ", ".join(f"{a}-{b}" for a, b in MODELS)
        field = "camera_model" if cm != "pinhole" else "distortion_model"
        raise InputError(src, f"{name}.{field}", f"Kalibr model {cm}-{dm} is not supported: its projection is not one of ours (supported: {supported}; "
                         "recalibrate with pinhole-radtan or pinhole-equi)")
    return MODELS[(cm, dm)]


def rig_from_kalibr(path) -> Rig:
    """Read a Kalibr camchain YAML as a validated :class:`Rig` (see the module docstring)."""
    data = load_yaml(path)
    names = _camera_names(path, data)
    blocks = [data[n] for n in names]
    for n, d in zip(names, blocks):
        if not isinstance(d, dict):
            raise InputError(path, n, f"expected a mapping of camera fields, got {type(d).__name__}")
    imu_body = "T_cam_imu" in blocks[0]
    T_c_b = []  # body -> camera, per camera
    for i, (n, d) in enumerate(zip(names, blocks)):
        chained = None
        if i > 0:
            if "T_cn_cnm1" in d:
                chained = parse_pose(path, f"{n}.T_cn_cnm1", d["T_cn_cnm1"]) @ T_c_b[i - 1]
            elif not (imu_body and "T_cam_imu" in d):
                raise InputError(path, f"{n}.T_cn_cnm1", f"missing field: the transform from cam{i - 1} to {n} (or T_cam_imu, when cam0 has one)")
        if i == 0:
            T_c_b.append(parse_pose(path, f"{n}.T_cam_imu", d["T_cam_imu"]) if imu_body else np.eye(4))
        elif imu_body and "T_cam_imu" in d:
            direct = parse_pose(path, f"{n}.T_cam_imu", d["T_cam_imu"])
            if chained is not None:
                dt, dr = pose_distance(direct, chained)
                if dt > CHAIN_TOLERANCE[0] or dr > CHAIN_TOLERANCE[1]:
                    warn(path, f"{n}: T_cam_imu and T_cn_cnm1 x cam{i - 1}'s T_cam_imu differ by {dt * 1e3:.2f} mm and {np.degrees(dr):.3f} deg; using T_cam_imu")
            T_c_b.append(direct)
        else:
            T_c_b.append(chained)
    cameras = []
    for i, (n, d) in enumerate(zip(names, blocks)):
        model = _model(path, n, d)
        for key in ("intrinsics", "resolution"):
            if key not in d:
                raise InputError(path, f"{n}.{key}", "missing field")
        cam = {"name": n, "model": model, "resolution": d["resolution"], "intrinsics": d["intrinsics"], "distortion": d.get("distortion_coeffs", []) if d.get("distortion_model", "none") != "none" else []}
        if "timeshift_cam_imu" in d:
            if isinstance(d["timeshift_cam_imu"], bool) or not isinstance(d["timeshift_cam_imu"], (int, float)):
                raise InputError(path, f"{n}.timeshift_cam_imu", f"expected a number of seconds, got {d['timeshift_cam_imu']!r}")
            cam["time_offset"] = 0.0 - float(d["timeshift_cam_imu"])  # t_cam = t_imu - timeshift (0.0 - : no negative zero)
        if "rostopic" in d:
            cam["topic"] = d["rostopic"]
        try:
            spec: CameraSpec = parse_camera(path, i, cam)
        except InputError as e:  # say Kalibr's field names
            msg = str(e).replace(f"cameras[{i}].distortion", f"{n}.distortion_coeffs").replace(f"cameras[{i}].time_offset", f"{n}.timeshift_cam_imu").replace(f"cameras[{i}].topic", f"{n}.rostopic").replace(f"cameras[{i}].", f"{n}.")
            raise InputError(None, None, msg) from None
        spec.T_b_c = invert(T_c_b[i])
        cameras.append(spec)
    rig = Rig(cameras)
    rig_from_dict(rig.to_dict(), src=path)  # the same checks as a rig file (names, poses)
    return rig


def load_any_rig(path) -> Rig:
    """A rig YAML file, or a Kalibr camchain (recognized by its ``cam0:`` block)."""
    data = load_yaml(path)
    if isinstance(data, dict) and "cam0" in data and "cameras" not in data:
        return rig_from_kalibr(path)
    return rig_from_dict(data, src=path)
