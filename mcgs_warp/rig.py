"""Camera rigs: per-camera model, intrinsics, distortion, resolution, extrinsic ``T_b_c``
and time offset, read from and written to YAML.

Format (``configs/rig_*.yaml``)::

    cameras:
      - name: front                      # optional, default cam<i>
        model: pinhole                   # pinhole | fisheye | equirectangular
        resolution: [320, 240]           # width, height (pixels)
        intrinsics: [fx, fy, cx, cy]     # pixels; optional for equirectangular
        distortion: [k1, k2, p1, p2, k3] # pinhole: up to 5 (OpenCV radtan); fisheye: k1..k4
        T_b_c:                           # camera -> body, either a 4x4 matrix (list of rows) ...
          translation: [x, y, z]         # ... or translation (m) + quaternion (x, y, z, w)
          quaternion: [qx, qy, qz, qw]
        time_offset: 0.0                 # s, camera clock = rig clock + time_offset
        topic: /cam0/image_raw           # optional: the camera's image topic in a ROS bag

Every field is validated; an error names the file, the camera and the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .geometry import matrix_to_quat, pose, rotation_error

_WARP_CAMERAS: dict = {}  # CameraSpec.warp_camera: parameters -> Camera struct

MODELS = ("pinhole", "fisheye", "equirectangular")
MAX_DISTORTION = {"pinhole": 5, "fisheye": 4, "equirectangular": 0}
CAMERA_FIELDS = {"name", "model", "resolution", "intrinsics", "distortion", "T_b_c", "time_offset", "topic"}


@dataclass
class CameraSpec:
    """One calibrated camera of a rig (host-side description)."""

    name: str
    model: str
    width: int  # px
    height: int  # px
    intrinsics: tuple[float, float, float, float] | None  # fx, fy, cx, cy (px); None: full-sphere equirectangular
    distortion: tuple[float, ...] = ()
    T_b_c: np.ndarray = field(default_factory=lambda: np.eye(4))  # camera -> body, m
    time_offset: float = 0.0  # s
    topic: str | None = None  # image topic in a ROS bag (data/rosbag.py)

    @property
    def pixels_per_radian(self) -> float:
        """Pixels per radian of view angle at the image centre: the focal length fx (pinhole,
        fisheye), width / 2 pi (equirectangular). A pixel at range r spans about r / this (m)."""
        if self.model == "equirectangular" or self.intrinsics is None:
            return self.width / (2 * np.pi)
        return float(self.intrinsics[0])

    def warp_camera(self):
        """The :class:`mcgs_warp.kernels.Camera` struct of this camera (made once per set of
        parameters: making one searches the distortion's valid radius; treat it as read-only)."""
        from .kernels import make_camera

        key = (self.model, int(self.width), int(self.height), tuple(float(v) for v in np.ravel(self.intrinsics)) if self.intrinsics is not None else None, tuple(float(v) for v in (() if self.distortion is None else self.distortion)))
        cam = _WARP_CAMERAS.get(key)
        if cam is None:
            cam = _WARP_CAMERAS[key] = make_camera(self.model, self.width, self.height, self.intrinsics, self.distortion)
        return cam


@dataclass
class Rig:
    cameras: list[CameraSpec]

    def __len__(self) -> int:
        return len(self.cameras)

    def warp_cameras(self) -> list:
        return [c.warp_camera() for c in self.cameras]

    def camera_poses(self, T_w_b: np.ndarray) -> np.ndarray:
        """Camera -> world poses ``T_w_c = T_w_b @ T_b_c``: [..., 4, 4] -> [..., C, 4, 4]."""
        T_b_c = np.stack([c.T_b_c for c in self.cameras])
        return np.asarray(T_w_b)[..., None, :, :] @ T_b_c

    def subset(self, indices) -> "Rig":
        return Rig([self.cameras[i] for i in indices])

    def to_dict(self) -> dict:
        out = []
        for c in self.cameras:
            d = {"name": c.name, "model": c.model, "resolution": [c.width, c.height]}
            if c.intrinsics is not None:
                d["intrinsics"] = [float(v) for v in c.intrinsics]
            if c.distortion:
                d["distortion"] = [float(v) for v in c.distortion]
            d["T_b_c"] = {
                "translation": [float(v) for v in c.T_b_c[:3, 3]],
                "quaternion": [float(v) for v in matrix_to_quat(c.T_b_c[:3, :3])],
            }
            d["time_offset"] = float(c.time_offset)
            if c.topic is not None:
                d["topic"] = c.topic
            out.append(d)
        return {"cameras": out}


# ----------------------------------------------------------------------------------------
# Validation helpers (each raises InputError naming source and field).


def _numbers(src, fld, value, count=None, max_count=None, integer=False):
    if not isinstance(value, (list, tuple)):
        raise InputError(src, fld, f"expected a list of numbers, got {type(value).__name__} {value!r}")
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InputError(src, fld, f"expected finite numbers, got {v!r}")
        if integer and (not float(v).is_integer()):
            raise InputError(src, fld, f"expected integers, got {v!r}")
    if count is not None and len(value) != count:
        raise InputError(src, fld, f"expected {count} numbers, got {len(value)}")
    if max_count is not None and len(value) > max_count:
        raise InputError(src, fld, f"expected at most {max_count} numbers, got {len(value)}")
    return [int(v) if integer else float(v) for v in value]


def _number(src, fld, value):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(src, fld, f"expected a finite number, got {value!r}")
    return float(value)


def parse_pose(src, fld, value) -> np.ndarray:
    """A 4x4 rigid transform from a list of 4 rows or ``{translation, quaternion}``."""
    if isinstance(value, dict):
        extra = set(value) - {"translation", "quaternion"}
        if extra:
            raise InputError(src, f"{fld}.{sorted(extra)[0]}", "unexpected field (expected translation and quaternion)")
        for key in ("translation", "quaternion"):
            if key not in value:
                raise InputError(src, f"{fld}.{key}", "missing field")
        t = _numbers(src, f"{fld}.translation", value["translation"], count=3)
        q = np.array(_numbers(src, f"{fld}.quaternion", value["quaternion"], count=4))
        norm = np.linalg.norm(q)
        if abs(norm - 1.0) > 1e-3:
            raise InputError(src, f"{fld}.quaternion", f"expected a unit quaternion (x, y, z, w), got norm {norm:.4f}")
        return pose(t, q)
    if isinstance(value, (list, tuple)) and len(value) == 16 and not isinstance(value[0], (list, tuple)):
        value = [value[4 * r : 4 * r + 4] for r in range(4)]
    if not isinstance(value, (list, tuple)) or len(value) != 4:
        raise InputError(src, fld, "expected a 4x4 matrix (4 rows of 4 numbers) or {translation, quaternion}")
    T = np.array([_numbers(src, f"{fld}[{r}]", row, count=4) for r, row in enumerate(value)])
    if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-6:
        raise InputError(src, f"{fld}[3]", f"expected last row [0, 0, 0, 1], got {T[3].tolist()}")
    why = rotation_error(T[:3, :3])
    if why:
        raise InputError(src, fld, why)
    return T


def parse_camera(src, index: int, d) -> CameraSpec:
    base = f"cameras[{index}]"
    if not isinstance(d, dict):
        raise InputError(src, base, f"expected a mapping of camera fields, got {type(d).__name__}")
    extra = set(d) - CAMERA_FIELDS
    if extra:
        raise InputError(src, f"{base}.{sorted(extra)[0]}", f"unexpected field (allowed: {', '.join(sorted(CAMERA_FIELDS))})")
    for key in ("model", "resolution"):
        if key not in d:
            raise InputError(src, f"{base}.{key}", "missing field")
    name = d.get("name", f"cam{index}")
    if not isinstance(name, str) or not name:
        raise InputError(src, f"{base}.name", f"expected a non-empty string, got {name!r}")
    model = d["model"]
    if model not in MODELS:
        raise InputError(src, f"{base}.model", f"expected one of {', '.join(MODELS)}, got {model!r}")
    w, h = _numbers(src, f"{base}.resolution", d["resolution"], count=2, integer=True)
    if w <= 0 or h <= 0:
        raise InputError(src, f"{base}.resolution", f"expected positive width and height, got {w}x{h}")
    intr = d.get("intrinsics")
    if intr is None:
        if model != "equirectangular":
            raise InputError(src, f"{base}.intrinsics", "missing field (expected [fx, fy, cx, cy])")
    else:
        intr = _numbers(src, f"{base}.intrinsics", intr, count=4)
        if intr[0] <= 0 or intr[1] <= 0:
            raise InputError(src, f"{base}.intrinsics", f"expected positive focal lengths, got fx={intr[0]}, fy={intr[1]}")
        intr = tuple(intr)
    dist = tuple(_numbers(src, f"{base}.distortion", d.get("distortion", []), max_count=MAX_DISTORTION[model]))
    T_b_c = parse_pose(src, f"{base}.T_b_c", d["T_b_c"]) if "T_b_c" in d else np.eye(4)
    offset = _number(src, f"{base}.time_offset", d.get("time_offset", 0.0))
    topic = d.get("topic")
    if topic is not None and (not isinstance(topic, str) or not topic.strip()):
        raise InputError(src, f"{base}.topic", f"expected a ROS topic name like /cam0/image_raw, got {topic!r}")
    return CameraSpec(name, model, w, h, intr, dist, T_b_c, offset, topic)


def rig_from_dict(data, src="<rig>") -> Rig:
    if not isinstance(data, dict):
        raise InputError(src, None, f"expected a mapping with a 'cameras' list, got {type(data).__name__}")
    extra = set(data) - {"cameras"}
    if extra:
        raise InputError(src, sorted(extra)[0], "unexpected field (expected only 'cameras')")
    cams = data.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise InputError(src, "cameras", "expected a non-empty list of cameras")
    rig = Rig([parse_camera(src, i, c) for i, c in enumerate(cams)])
    names = [c.name for c in rig.cameras]
    for i, n in enumerate(names):
        if names.index(n) != i:
            raise InputError(src, f"cameras[{i}].name", f"duplicate camera name {n!r}")
    return rig


def load_yaml(path):
    """Parse a YAML file; syntax errors become :class:`InputError` naming the line."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "file not found")
    text = path.read_text(errors="replace")
    # OpenCV-style files (EuRoC) start with a '%YAML:1.0' directive that PyYAML rejects.
    text = "\n".join("" if line.startswith("%YAML") else line for line in text.splitlines())
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise InputError(path, None, f"YAML syntax error: {where}{problem}") from None


def load_rig(path) -> Rig:
    """Read and validate a rig YAML file."""
    return rig_from_dict(load_yaml(path), src=path)


def save_rig(rig: Rig, path) -> None:
    """Write ``rig`` as YAML (atomically)."""
    import yaml

    from .io import atomic_write

    with atomic_write(path) as f:
        yaml.safe_dump(rig.to_dict(), f, sort_keys=False, default_flow_style=None)
