"""Waymo Open Dataset v2 (Parquet release) reader: the front three or all five cameras as a rig.

Layout (one file per segment and component; the folder of a split, e.g. ``training/``)::

    ROOT/camera_image/<segment>.parquet        one row per (frame, camera): JPEG and its keys
    ROOT/camera_calibration/<segment>.parquet  one row per camera: intrinsics, extrinsic, size
    ROOT/vehicle_pose/<segment>.parquet        optional: one row per frame, vehicle -> world

Columns read (the v2 naming: keys ``key.<field>``, component fields ``[<Component>].<path>``,
built by ``component.py``), as defined in github.com/waymo-research/waymo-open-dataset (read at
99a4cb3), ``src/waymo_open_dataset/v2/``: ``perception/base.py`` (keys ``key.segment_context_name``
string, ``key.frame_timestamp_micros`` int64, ``key.camera_name`` int8; the repository's test data
stores the enum's name, also read), ``perception/camera_image.py`` (``[CameraImageComponent].image``,
JPEG bytes; optional ``[CameraImageComponent].pose_timestamp``, s), ``perception/context.py``
(``[CameraCalibrationComponent].intrinsic.{f_u,f_v,c_u,c_v,k1,k2,p1,p2,k3}``,
``.extrinsic.transform``, ``.width``, ``.height``), ``perception/pose.py``
(``[VehiclePoseComponent].world_from_vehicle.transform``) and ``column_types.py`` (a ``Transform``
is 16 float64, a row-major 4x4).

Frames: the images of one frame share ``key.frame_timestamp_micros`` (us -> s on the rig clock);
a timestamp that lacks one of the chosen cameras is dropped (one warning). Cameras (``key.camera_name``,
``CameraName`` in camera_image.py): 1 FRONT, 2 FRONT_LEFT, 3 FRONT_RIGHT, 4 SIDE_LEFT,
5 SIDE_RIGHT; ``cameras="front3"`` (default, the paper's rig) is FRONT_LEFT, FRONT, FRONT_RIGHT,
``"all"`` is SIDE_LEFT, FRONT_LEFT, FRONT, FRONT_RIGHT, SIDE_RIGHT (left to right; the side
cameras have fewer rows).

Frames and poses: the rig body is Waymo's vehicle frame (x forward, y left, z up, m). A Waymo
camera frame is x forward (optical axis), y left, z up, and projects as ``u_n = -y/x``,
``v_n = -z/x``, OpenCV radial-tangential distortion, ``u = f_u u_nd + c_u``
(``wdl_limited/camera/camera_model.cc``); ours is OpenCV's (x right, y down, z forward), so
``T_b_c = extrinsic @ [R_WAYMO_CV 0; 0 1]`` with ``p_waymo = R_WAYMO_CV @ p_ours``, and the
intrinsics and distortion carry over unchanged. Ground truth ``T_w_b`` is ``world_from_vehicle``
at the frame timestamp (world: the segment's map frame, z up). Cameras are rolling-shutter and
fire as the lidar sweeps past; each image's own capture time (``pose_timestamp``) is kept in
``image_timestamps`` [K, C] (s, NaN where absent) but the rig treats a frame as synchronous.

Lazy reading: the constructor reads the key columns and the small tables only; ``load_frame``
streams the image column in small batches (``ParquetFile.iter_batches``, 1 MiB read buffer), so
about one frame's JPEGs are in memory at a time; reading frames in order costs one pass over the
file. pyarrow is an optional dependency (``pip install .[waymo]``), imported on use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError, warn
from ..geometry import rotation_error
from ..rig import CameraSpec, Rig
from .sequence import Frame, Sequence
from .trajectory import Trajectory

COMPONENTS = ("camera_image", "camera_calibration", "vehicle_pose")  # vehicle_pose is optional
CAMERA_NAMES = {1: "FRONT", 2: "FRONT_LEFT", 3: "FRONT_RIGHT", 4: "SIDE_LEFT", 5: "SIDE_RIGHT"}
CAMERA_SETS = {"front3": (2, 1, 3), "all": (4, 2, 1, 3, 5)}  # camera ids, left to right

KEY_SEGMENT = "key.segment_context_name"
KEY_TIME = "key.frame_timestamp_micros"
KEY_CAMERA = "key.camera_name"
IMAGE = "[CameraImageComponent].image"
POSE_TIME = "[CameraImageComponent].pose_timestamp"
_CALIB = "[CameraCalibrationComponent]"
INTRINSIC = tuple(f"{_CALIB}.intrinsic.{k}" for k in ("f_u", "f_v", "c_u", "c_v", "k1", "k2", "p1", "p2", "k3"))
EXTRINSIC = f"{_CALIB}.extrinsic.transform"
WIDTH, HEIGHT = f"{_CALIB}.width", f"{_CALIB}.height"
VEHICLE_POSE = "[VehiclePoseComponent].world_from_vehicle.transform"

#: Waymo camera axes (x forward, y left, z up) from ours (x right, y down, z forward): p_waymo = R @ p_ours
R_WAYMO_CV = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
BATCH_ROWS = 8  # images decoded from Parquet per batch
READ_BUFFER = 1 << 20  # bytes: Parquet read buffer (streams a column chunk instead of loading it whole)


def is_waymo(path) -> bool:
    path = Path(path)
    return (path / "camera_image").is_dir() and (path / "camera_calibration").is_dir()


def waymo_segments(root) -> list[str]:
    """Segment context names with a ``camera_image`` file under ``root``, sorted."""
    return sorted(p.stem for p in (Path(root) / "camera_image").glob("*.parquet"))


def _parquet():
    """``pyarrow.parquet``, or an InputError saying how to install it."""
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise InputError(None, "pyarrow", "reading the Waymo Open Dataset (Parquet) needs pyarrow: pip install .[waymo]") from None
    return pq


def _open(path: Path):
    """A ``ParquetFile`` that streams its column chunks; unreadable files are InputErrors."""
    pq = _parquet()
    if not path.is_file():
        raise InputError(path, None, "file not found (each Waymo v2 component holds one <segment>.parquet)")
    try:
        return pq.ParquetFile(path, buffer_size=READ_BUFFER, pre_buffer=False)
    except Exception as e:  # pyarrow raises ArrowInvalid / OSError on a cut or foreign file
        raise InputError(path, None, f"not a readable Parquet file (truncated or corrupt?): {e}") from None


def _read_columns(pf, path: Path, columns) -> dict:
    """The named columns of the whole file as Python lists (only for small or key columns)."""
    names = set(pf.schema_arrow.names)
    for c in columns:
        if c not in names:
            raise InputError(path, c, "missing column (expected the Waymo Open Dataset v2 schema)")
    try:
        table = pf.read(columns=list(columns), use_threads=False)
    except Exception as e:
        raise InputError(path, None, f"could not read columns (truncated or corrupt?): {e}") from None
    return {c: table.column(c).to_pylist() for c in columns}


def _camera_id(value, path: Path) -> int:
    """A ``key.camera_name`` value: the int8 of the release, or the enum's name / number as a string."""
    if isinstance(value, str):
        by_name = {n: i for i, n in CAMERA_NAMES.items()}
        value = by_name.get(value, int(value) if value.strip().isdigit() else value)
    if isinstance(value, (int, np.integer)) and int(value) in CAMERA_NAMES:
        return int(value)
    known = ", ".join(f"{i} {n}" for i, n in CAMERA_NAMES.items())
    raise InputError(path, KEY_CAMERA, f"unknown camera {value!r}: expected one of {known}")


def _transforms(values, path: Path, column: str, what: str) -> np.ndarray:
    """Row-major 4x4 transforms [N,4,4] (float64) from lists of 16 numbers, validated."""
    try:
        T = np.array(values, dtype=np.float64).reshape(len(values), 4, 4)
    except (TypeError, ValueError):
        raise InputError(path, column, "expected 16 numbers per row (a row-major 4x4 transform)") from None
    for i, M in enumerate(T):
        why = None if np.abs(M[3] - [0, 0, 0, 1]).max() < 1e-6 else f"last row is {M[3].tolist()}, expected [0, 0, 0, 1]"
        why = why or rotation_error(M[:3, :3])
        if why:
            raise InputError(path, column, f"{what(i)}: {why}")
    return T


class WaymoSequence(Sequence):
    """One segment of a Waymo Open Dataset v2 folder (module docstring).

    ``segment``: a segment context name (default: the only one under ``root``);
    ``cameras``: ``"front3"`` or ``"all"``."""

    def __init__(self, root, segment: str | None = None, cameras: str = "front3"):
        self.root = Path(root)
        if cameras not in CAMERA_SETS:
            raise InputError(None, "--waymo-cameras", f"expected one of {' | '.join(CAMERA_SETS)}, got {cameras!r}")
        for comp in COMPONENTS[:2]:
            if not (self.root / comp).is_dir():
                raise InputError(self.root / comp, None, f"missing component folder (a Waymo v2 folder holds {', '.join(COMPONENTS)})")
        segments = waymo_segments(self.root)
        if segment is None:
            if len(segments) != 1:
                found = ", ".join(segments) if segments else "none"
                raise InputError(self.root / "camera_image", None, f"expected one segment or a choice (--segment NAME); segments: {found}")
            segment = segments[0]
        elif segment not in segments:
            raise InputError(self.root / "camera_image", segment, f"no such segment; segments: {', '.join(segments) or 'none'}")
        self.segment = self.name = segment
        self.ids = CAMERA_SETS[cameras]
        self.rig = Rig(self._read_calibration())
        self._read_frames()
        self.gravity = np.array([0.0, 0.0, -1.0])  # the world frame has z up
        self.groundtruth = self._read_poses()

    def _path(self, component: str) -> Path:
        return self.root / component / f"{self.segment}.parquet"

    def _read_calibration(self) -> list[CameraSpec]:
        path = self._path("camera_calibration")
        cols = _read_columns(_open(path), path, (KEY_SEGMENT, KEY_CAMERA, *INTRINSIC, EXTRINSIC, WIDTH, HEIGHT))
        rows = {}
        for r, seg in enumerate(cols[KEY_SEGMENT]):
            if seg == self.segment:
                cam = _camera_id(cols[KEY_CAMERA][r], path)
                if cam in rows:
                    raise InputError(path, KEY_CAMERA, f"camera {CAMERA_NAMES[cam]} is calibrated twice")
                rows[cam] = r
        specs = []
        for cam in self.ids:
            if cam not in rows:
                raise InputError(path, KEY_CAMERA, f"no calibration of camera {cam} {CAMERA_NAMES[cam]} (calibrated: {', '.join(CAMERA_NAMES[c] for c in sorted(rows)) or 'none'})")
            r = rows[cam]
            vals = [cols[c][r] for c in INTRINSIC]
            if any(v is None or not np.isfinite(v) for v in vals) or vals[0] <= 0 or vals[1] <= 0:
                raise InputError(path, f"{_CALIB}.intrinsic", f"camera {CAMERA_NAMES[cam]}: expected finite numbers and positive f_u, f_v, got {vals}")
            w, h = cols[WIDTH][r], cols[HEIGHT][r]
            if not w or not h or w <= 0 or h <= 0:
                raise InputError(path, f"{WIDTH}, {HEIGHT}", f"camera {CAMERA_NAMES[cam]}: expected a positive image size, got {w}x{h}")
            extrinsic = _transforms([cols[EXTRINSIC][r]], path, EXTRINSIC, lambda _: f"camera {CAMERA_NAMES[cam]}")[0]
            T_b_c = extrinsic.copy()
            T_b_c[:3, :3] = extrinsic[:3, :3] @ R_WAYMO_CV
            specs.append(CameraSpec(CAMERA_NAMES[cam], "pinhole", int(w), int(h), tuple(vals[:4]), tuple(vals[4:]), T_b_c))
        return specs

    def _read_frames(self) -> None:
        """Frame timestamps and, per frame and camera, the row of its image in camera_image."""
        path = self._path("camera_image")
        pf = _open(path)
        keys = [KEY_SEGMENT, KEY_TIME, KEY_CAMERA] + ([POSE_TIME] if POSE_TIME in pf.schema_arrow.names else [])
        cols = _read_columns(pf, path, keys)
        if IMAGE not in pf.schema_arrow.names:
            raise InputError(path, IMAGE, "missing column (expected the Waymo Open Dataset v2 schema)")
        row_of, when = {}, {}
        for r, seg in enumerate(cols[KEY_SEGMENT]):
            if seg != self.segment:
                continue
            key = (cols[KEY_TIME][r], _camera_id(cols[KEY_CAMERA][r], path))
            if key in row_of:
                raise InputError(path, f"{KEY_TIME} {key[0]}", f"two images of camera {CAMERA_NAMES[key[1]]}")
            row_of[key] = r
            when[key] = cols[POSE_TIME][r] if POSE_TIME in cols else None
        stamps = sorted({t for t, _ in row_of})
        full = [t for t in stamps if all((t, c) in row_of for c in self.ids)]
        if not full:
            names = ", ".join(CAMERA_NAMES[c] for c in self.ids)
            raise InputError(path, None, f"no frame of segment {self.segment} has an image from every chosen camera ({names})")
        if len(full) < len(stamps):
            warn(path, f"dropped {len(stamps) - len(full)} of {len(stamps)} frames that lack an image of a chosen camera")
        self._micros = np.array(full, dtype=np.int64)
        self.timestamps = self._micros * 1e-6
        self._rows = np.array([[row_of[t, c] for c in self.ids] for t in full], dtype=np.int64)  # [K, C]
        self.image_timestamps = np.array([[np.nan if when[t, c] is None else when[t, c] for c in self.ids] for t in full], dtype=np.float64)
        self._images = _ImageColumn(pf, path, IMAGE)

    def _read_poses(self) -> Trajectory | None:
        path = self._path("vehicle_pose")
        if not path.is_file():
            return None
        cols = _read_columns(_open(path), path, (KEY_SEGMENT, KEY_TIME, VEHICLE_POSE))
        rows = {t: r for r, (seg, t) in enumerate(zip(cols[KEY_SEGMENT], cols[KEY_TIME])) if seg == self.segment}
        stamps = sorted(rows)
        if not stamps:
            raise InputError(path, KEY_SEGMENT, f"no pose of segment {self.segment}")
        poses = _transforms([cols[VEHICLE_POSE][rows[t]] for t in stamps], path, VEHICLE_POSE, lambda i: f"{KEY_TIME} {stamps[i]}")
        return Trajectory(np.array(stamps, dtype=np.int64) * 1e-6, poses)

    def load_frame(self, k: int) -> Frame:
        import cv2

        path = self._path("camera_image")
        cells = self._images.read(self._rows[k])
        images = []
        for r, cam in zip(self._rows[k], self.rig.cameras):
            data = cells[int(r)]
            img = None if data is None else cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            where = f"{KEY_TIME} {self._micros[k]}, camera {cam.name}"
            if img is None:
                raise InputError(path, where, "could not decode the image (expected JPEG bytes)")
            if (img.shape[1], img.shape[0]) != (cam.width, cam.height):
                raise InputError(path, where, f"expected image size {cam.width}x{cam.height} (camera_calibration), got {img.shape[1]}x{img.shape[0]}")
            images.append(np.ascontiguousarray(img[..., ::-1], dtype=np.float32) / 255.0)
        return Frame(k, float(self.timestamps[k]), images, [None] * len(images))


class _ImageColumn:
    """Cells of one column of a Parquet file by row index, streamed in small batches.

    Keeps one batch (``BATCH_ROWS`` rows) and an iterator positioned after it: rows in the kept
    batch, or ahead of it in the same row group, are read by moving on; any other row restarts
    the iterator at that row's row group (so a jump skips whole row groups undecoded)."""

    def __init__(self, pf, path: Path, column: str):
        self.pf, self.path, self.column = pf, path, column
        sizes = [pf.metadata.row_group(g).num_rows for g in range(pf.metadata.num_row_groups)]
        self.starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)  # [G+1] first row of each group
        self._it, self._batch, self._at = None, None, 0  # kept batch and its first row

    def _group(self, row: int) -> int:
        return int(np.searchsorted(self.starts, row, side="right") - 1)

    def _restart(self, row: int) -> None:
        g = self._group(row)
        groups = list(range(g, len(self.starts) - 1))
        self._it = self.pf.iter_batches(batch_size=BATCH_ROWS, row_groups=groups, columns=[self.column], use_threads=False)
        self._batch, self._at = None, int(self.starts[g])

    def read(self, rows) -> dict:
        """{row: cell value} for the row indices ``rows``."""
        rows = sorted({int(r) for r in rows})
        end = self._at + (self._batch.num_rows if self._batch is not None else 0)  # next row the iterator yields
        in_batch = self._batch is not None and self._at <= rows[0] < end
        ahead = self._it is not None and rows[0] >= end and self._group(rows[0]) == self._group(end)
        if not (in_batch or ahead):
            self._restart(rows[0])
            end = self._at
        out = {}
        try:
            while True:
                if self._batch is not None:
                    col = self._batch.column(0)
                    out.update({r: col[r - self._at].as_py() for r in rows if self._at <= r < end})
                if len(out) == len(rows):
                    return out
                self._batch = next(self._it)
                self._at, end = end, end + self._batch.num_rows
        except StopIteration:
            raise InputError(self.path, self.column, f"row {rows[-1]} is missing (the file ends at row {end})") from None
        except InputError:
            raise
        except Exception as e:
            self._it = None
            raise InputError(self.path, self.column, f"could not read (truncated or corrupt?): {e}") from None
