"""EuRoC MAV dataset reader: the stereo pair as a 2-camera rig.

Layout (the sequence folder, or its ``mav0/`` folder)::

    mav0/cam0/data.csv        '#timestamp [ns],filename'
    mav0/cam0/data/<ns>.png   8-bit grey images
    mav0/cam0/sensor.yaml     T_BS (camera -> body/IMU), resolution, intrinsics, distortion
    mav0/cam1/...
    mav0/state_groundtruth_estimate0/data.csv   optional: t [ns], p (m), q (w, x, y, z), ...

``sensor.yaml`` files start with OpenCV's ``%YAML:1.0`` line, which PyYAML rejects;
:func:`mcgs_warp.rig.load_yaml` drops it. Frames are the timestamps both cameras
have: a cam1 image within 5 ms (``MAX_SYNC_DT``) of a cam0 image, nearest first, pairs
with it, so a software-synced or re-exported recording whose stamps differ by a little
still reads (a camera's ``time_offset``, camera clock = rig clock + offset, is removed
first); the frame's timestamp is cam0's. Images are replicated to RGB. Ground truth poses are of the body (IMU) frame,
the frame ``T_BS`` maps into, so they are ``T_w_b``.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..errors import InputError, warn
from ..geometry import pose
from ..rig import CameraSpec, Rig, load_yaml, parse_pose
from .sequence import MAX_SYNC_DT, MAX_UNMATCHED_FRACTION, Frame, Sequence
from .trajectory import Trajectory, nearest_timestamps

DISTORTION_MODELS = {"radial-tangential": "pinhole", "radtan": "pinhole", "equidistant": "fisheye"}


def _mav0(path: Path) -> Path:
    return path / "mav0" if (path / "mav0").is_dir() else path


def is_euroc(path) -> bool:
    root = _mav0(Path(path))
    return (root / "cam0" / "data.csv").is_file() or (root / "cam0" / "sensor.yaml").is_file()


def read_csv_rows(path: Path, min_cols: int):
    """Rows of a EuRoC csv (comment lines skipped), each with at least ``min_cols`` fields."""
    if not path.is_file():
        raise InputError(path, None, "file not found")
    rows = []
    with open(path, newline="", errors="replace") as f:
        for lineno, row in enumerate(csv.reader(f), 1):
            if not row or row[0].lstrip().startswith("#"):
                continue
            if len(row) < min_cols:
                raise InputError(path, f"line {lineno}", f"expected at least {min_cols} comma-separated fields, got {len(row)}")
            rows.append((lineno, [c.strip() for c in row]))
    if not rows:
        raise InputError(path, None, "no data rows")
    return rows


def read_sensor(path: Path, name: str) -> CameraSpec:
    data = load_yaml(path)
    if not isinstance(data, dict):
        raise InputError(path, None, "expected a mapping of camera fields")
    for key in ("T_BS", "resolution", "intrinsics"):
        if key not in data:
            raise InputError(path, key, "missing field")
    tbs = data["T_BS"]
    if not isinstance(tbs, dict) or "data" not in tbs:
        raise InputError(path, "T_BS", "expected a mapping with rows, cols and data (16 numbers)")
    data_list = tbs["data"]
    if not isinstance(data_list, list) or len(data_list) != 16:
        raise InputError(path, "T_BS.data", f"expected 16 numbers, got {len(data_list) if isinstance(data_list, list) else data_list!r}")
    T_b_c = parse_pose(path, "T_BS.data", data_list)
    dmodel = data.get("distortion_model", "radial-tangential")
    if dmodel not in DISTORTION_MODELS:
        raise InputError(path, "distortion_model", f"expected one of {', '.join(DISTORTION_MODELS)}, got {dmodel!r}")
    from ..rig import parse_camera

    cam = {
        "name": name,
        "model": DISTORTION_MODELS[dmodel],
        "resolution": data["resolution"],
        "intrinsics": data["intrinsics"],
        "distortion": data.get("distortion_coefficients", []),
    }
    try:
        spec = parse_camera(path, 0, cam)
    except InputError as e:  # re-label the field with EuRoC's names
        msg = str(e).replace("cameras[0].distortion", "distortion_coefficients").replace("cameras[0].", "")
        raise InputError(None, None, msg) from None
    spec.T_b_c = T_b_c
    return spec


def read_groundtruth(path: Path) -> Trajectory:
    rows = read_csv_rows(path, 8)
    t, p, q = [], [], []
    for lineno, row in rows:
        try:
            vals = [float(v) for v in row[:8]]
        except ValueError:
            raise InputError(path, f"line {lineno}", "expected numbers") from None
        if not np.all(np.isfinite(vals)):
            raise InputError(path, f"line {lineno}", "contains NaN or Inf")
        if t and vals[0] * 1e-9 <= t[-1]:
            raise InputError(path, f"line {lineno}", "timestamps must increase")
        t.append(vals[0] * 1e-9)
        p.append(vals[1:4])
        q.append([vals[5], vals[6], vals[7], vals[4]])  # (w, x, y, z) -> (x, y, z, w)
    return Trajectory(np.array(t), pose(np.array(p), np.array(q)))


class EurocSequence(Sequence):
    """``rig``, where given, replaces the ``sensor.yaml`` calibrations (its time offsets pair the images)."""

    def __init__(self, path, rig: Rig | None = None):
        self.root = _mav0(Path(path))
        self.name = Path(path).name
        cams, stamps, files = [], [], []
        for i in (0, 1):
            folder = self.root / f"cam{i}"
            if not folder.is_dir():
                raise InputError(folder, None, "missing camera folder (EuRoC stereo needs cam0 and cam1)")
            cams.append(read_sensor(folder / "sensor.yaml", f"cam{i}") if rig is None else rig.cameras[i])
            by_stamp = {}
            for lineno, row in read_csv_rows(folder / "data.csv", 2):
                try:
                    ns = int(row[0])
                except ValueError:
                    raise InputError(folder / "data.csv", f"line {lineno}", f"expected an integer timestamp [ns], got {row[0]!r}") from None
                by_stamp[ns] = folder / "data" / row[1]
            stamps.append(by_stamp)
            files.append(by_stamp)
        ns = [np.array(sorted(st), dtype=np.int64) for st in stamps]
        t = [(n - ns[0][0]) * 1e-9 - c.time_offset for n, c in zip(ns, cams)]  # rig clock, relative to cam0's first image
        j = nearest_timestamps(t[0], t[1], MAX_SYNC_DT)
        i = np.nonzero(j >= 0)[0]
        _, first = np.unique(j[i], return_index=True)  # one cam0 image per cam1 image
        i = np.sort(i[first])
        if not len(i):
            raise InputError(self.root, None, f"cam0 and cam1 have no images within {MAX_SYNC_DT * 1e3:g} ms of each other")
        self._check_dropped(len(ns[0]) + len(ns[1]) - len(i), len(i), len(ns[0]), len(ns[1]))
        self.rig = Rig(cams)
        self.gravity = np.array([0.0, 0.0, -1.0])  # the ground truth's world frame has z up
        self._ns = list(zip(ns[0][i].tolist(), ns[1][j[i]].tolist()))
        self._files = files
        self.timestamps = ns[0][i] * 1e-9 - cams[0].time_offset
        gt = self.root / "state_groundtruth_estimate0" / "data.csv"
        self.groundtruth = read_groundtruth(gt) if gt.is_file() else None

    def _check_dropped(self, total: int, kept: int, n0: int, n1: int) -> None:
        """Frames only one camera has are dropped: say how many; more than 10 % of all frames
        (and more than one, for tiny sequences) means the two lists do not belong together."""
        dropped = total - kept
        if dropped == 0:
            return
        what = f"dropped {dropped} of {total} frames that only one camera has (cam0/data.csv lists {n0}, cam1/data.csv lists {n1})"
        if dropped > max(1, MAX_UNMATCHED_FRACTION * total):
            raise InputError(self.root, None, f"{what}: more than {MAX_UNMATCHED_FRACTION:.0%} do not pair up; check that both lists come from this recording")
        warn(self.root, what)

    def load_frame(self, k: int) -> Frame:
        from ..io import read_image

        images = [read_image(self._files[i][ns], (c.width, c.height)) for i, (ns, c) in enumerate(zip(self._ns[k], self.rig.cameras))]
        return Frame(k, float(self.timestamps[k]), images, [None, None])
