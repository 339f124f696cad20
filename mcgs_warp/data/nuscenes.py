"""nuScenes reader: one scene's six cameras as a rig, at the 2 Hz keyframes or the ~12 Hz sweeps.

Layout (the dataset root; schema: github.com/nutonomy/nuscenes-devkit ``docs/schema_nuscenes.md``, read at d9de17a)::

    v1.0-<version>/scene.json              name, first_sample_token, ... (one record per scene)
    v1.0-<version>/sample.json             keyframes: token, scene_token, timestamp (us)
    v1.0-<version>/sample_data.json        one record per image (and lidar/radar sweep): sample_token, ego_pose_token,
                                           calibrated_sensor_token, filename, width, height,
                                           timestamp (us), is_key_frame
    v1.0-<version>/calibrated_sensor.json  sensor_token, translation (m), rotation (w, x, y, z),
                                           camera_intrinsic (3x3): sensor -> ego
    v1.0-<version>/ego_pose.json           translation (m), rotation (w, x, y, z): ego -> global
    v1.0-<version>/sensor.json             channel (CAM_FRONT, ...), modality (camera, lidar, radar)
    v1.0-<version>/log.json, ...           not read
    samples/CAM_*/*.jpg, sweeps/CAM_*/*.jpg  keyframe and sweep images (sample_data.filename)

Frames and poses: the rig body is the ego vehicle frame (x forward, y left, z up); a camera's
``T_b_c`` is its calibrated_sensor (camera frames are OpenCV's: x right, y down, z forward;
images come undistorted, so the model is a plain pinhole). Rig cameras, in this order:
CAM_FRONT_LEFT, CAM_FRONT, CAM_FRONT_RIGHT, CAM_BACK_RIGHT, CAM_BACK, CAM_BACK_LEFT.

The cameras are not synchronized: each fires as the 20 Hz lidar sweeps past it, so the six
images of one sweep are up to about 50 ms apart. Rig frames: ``sweeps=False`` (default) takes
the keyframes (each sample's six key images, grouped by the dataset itself); ``sweeps=True``
takes every CAM_FRONT image and, per other camera, the image nearest in time within
``MAX_SPREAD`` (each image once), dropping frames with a camera missing (one warning). A
frame's timestamp and ground truth ``T_w_b`` are those of its CAM_FRONT image (its ego_pose,
global map frame, z up), exact for CAM_FRONT. Treating the other images as simultaneous puts
camera c where the body was at CAM_FRONT's time, not at its own: off by ``v |dt_c|`` (plus
``omega |dt_c|`` of rotation), e.g. 0.4 m at 10 m/s and 40 ms, 1.1 deg at 0.5 rad/s. The reader
keeps each image's own time and ego pose (``image_timestamps`` [K, C] s, ``image_poses``
[K, C, 4, 4]) and that displacement (``sync_error`` [K] m, largest over the cameras), and says
how large it is (one warning) when the cameras are more than ``MAX_SYNC_DT`` apart.
Timestamps are microseconds (-> s).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError, warn
from ..geometry import pose
from ..rig import CameraSpec, Rig
from .sequence import MAX_SYNC_DT, Frame, Sequence
from .trajectory import Trajectory, nearest_timestamps

CHANNELS = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT")
REFERENCE = "CAM_FRONT"  # the rig frame's time and pose
TABLES = ("scene", "sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor")
FIELDS = {
    "scene": ("token", "name"),
    "sample": ("token", "scene_token", "timestamp"),
    "sample_data": ("token", "sample_token", "ego_pose_token", "calibrated_sensor_token", "filename", "width", "height", "timestamp", "is_key_frame"),
    "calibrated_sensor": ("token", "sensor_token", "translation", "rotation", "camera_intrinsic"),
    "ego_pose": ("token", "translation", "rotation"),
    "sensor": ("token", "channel", "modality"),
}
MAX_SPREAD = 0.05  # s: sweeps mode, an image this close to CAM_FRONT's joins its frame (one lidar revolution)
LISTED_SCENES = 12  # scene names an error lists


def nuscenes_versions(root) -> list[str]:
    """The ``v1.0-*`` table folders under ``root`` (those with a scene.json), sorted."""
    return sorted(p.name for p in Path(root).glob("v1.0-*") if (p / "scene.json").is_file())


def is_nuscenes(path) -> bool:
    return bool(nuscenes_versions(path))


def nuscenes_scenes(root) -> list[str]:
    """The scene names (``scene-0061``, ...) of every ``v1.0-*`` table folder under ``root``,
    sorted, each once (v1.0-mini's scenes are also in v1.0-trainval)."""
    return sorted({s["name"] for v in nuscenes_versions(root) for s in read_table(Path(root) / v, "scene")})


def read_table(folder: Path, name: str) -> list[dict]:
    """One JSON table: a list of records, each with the fields :data:`FIELDS` names."""
    path = folder / f"{name}.json"
    if not path.is_file():
        raise InputError(path, None, f"missing table (nuScenes needs {', '.join(t + '.json' for t in TABLES)})")
    try:
        with open(path, encoding="utf-8") as f:
            rows = json.load(f)
    except json.JSONDecodeError as e:
        raise InputError(path, f"line {e.lineno}, column {e.colno}", f"not valid JSON (truncated?): {e.msg}") from None
    except UnicodeDecodeError:
        raise InputError(path, None, "not valid JSON (not UTF-8 text)") from None
    if not isinstance(rows, list):
        raise InputError(path, None, f"expected a list of records, got {type(rows).__name__}")
    need = set(FIELDS[name])
    for i, r in enumerate(rows):
        if not isinstance(r, dict) or not need <= r.keys():
            missing = sorted(need - r.keys()) if isinstance(r, dict) else ["(not a record)"]
            raise InputError(path, f"[{i}]", f"missing field {missing[0]}")
    return rows


def _by_token(rows: list[dict]) -> dict:
    return {r["token"]: r for r in rows}


def _lookup(table: dict, token, path: Path, field: str):
    if token not in table:
        raise InputError(path, field, f"points to a missing record {token!r}")
    return table[token]


def _transform(rec: dict, path: Path, what: str) -> np.ndarray:
    """4x4 pose of a record's ``translation`` (m) and ``rotation`` (w, x, y, z)."""
    try:
        t = np.array(rec["translation"], dtype=np.float64).reshape(3)
        w, x, y, z = np.array(rec["rotation"], dtype=np.float64).reshape(4)
    except (TypeError, ValueError):
        raise InputError(path, what, "expected translation [3] and rotation [4] (w, x, y, z)") from None
    norm = np.linalg.norm([w, x, y, z])
    if not (np.all(np.isfinite(t)) and abs(norm - 1.0) < 1e-3):
        raise InputError(path, what, f"expected a finite translation and a unit quaternion, got |q| = {norm:.4f}")
    return pose(t, [x, y, z, w])


class NuScenesSequence(Sequence):
    """One nuScenes scene (module docstring). ``scene``: its name, e.g. ``scene-0061`` (default:
    the only one); ``version``: the table folder, e.g. ``v1.0-mini`` (default: the only one, or
    the one holding ``scene``); ``sweeps``: all ~12 Hz images instead of the 2 Hz keyframes."""

    def __init__(self, root, scene: str | None = None, version: str | None = None, sweeps: bool = False):
        self.root = Path(root)
        self.tables = self._find_tables(version, scene)
        self.version = self.tables.name
        scenes = read_table(self.tables, "scene")
        names = [s["name"] for s in scenes]
        if scene is None and len(scenes) != 1:
            raise InputError(self.tables / "scene.json", None, f"holds {len(scenes)} scenes: choose one with --segment NAME ({_listing(names)})")
        chosen = scenes[0] if scene is None else next((s for s in scenes if s["name"] == scene), None)
        if chosen is None:
            raise InputError(self.tables / "scene.json", scene, f"no such scene; scenes: {_listing(names)}")
        self.name = chosen["name"]
        frames = self._group(chosen, sweeps)
        self._read_frames(frames)
        self.gravity = np.array([0.0, 0.0, -1.0])  # the global frame has z up

    def _find_tables(self, version: str | None, scene: str | None) -> Path:
        versions = nuscenes_versions(self.root)
        if version is not None:
            if version not in versions:
                raise InputError(self.root / version, None, f"missing table folder (with scene.json); found: {', '.join(versions) or 'none'}")
            return self.root / version
        if scene is not None and len(versions) > 1:
            holding = [v for v in versions if scene in {s["name"] for s in read_table(self.root / v, "scene")}]
            if not holding:
                raise InputError(self.root, scene, f"no such scene in {', '.join(versions)}")
            if len(holding) > 1:
                raise InputError(self.root, scene, f"the scene is in {len(holding)} table folders ({', '.join(holding)}); expected one: keep one of them under this root")
            versions = holding
        if len(versions) != 1:
            raise InputError(self.root, None, f"expected one v1.0-* table folder, found {', '.join(versions) or 'none'}: name the scene (--segment) to pick its version")
        return self.root / versions[0]

    def _group(self, scene: dict, sweeps: bool) -> list[list[dict]]:
        """The rig frames: per frame the sample_data records of the six cameras, in :data:`CHANNELS` order."""
        sd_path = self.tables / "sample_data.json"
        samples = sorted((s for s in read_table(self.tables, "sample") if s["scene_token"] == scene["token"]), key=lambda s: s["timestamp"])
        if not samples:
            raise InputError(self.tables / "sample.json", scene["name"], "the scene has no samples")
        sensors = _by_token(read_table(self.tables, "sensor"))
        self._calibrations = calibs = _by_token(read_table(self.tables, "calibrated_sensor"))
        in_scene = {s["token"] for s in samples}
        images = {c: [] for c in CHANNELS}
        for sd in read_table(self.tables, "sample_data"):
            if sd["sample_token"] not in in_scene or not (sweeps or sd["is_key_frame"]):
                continue
            cs = _lookup(calibs, sd["calibrated_sensor_token"], sd_path, f"{sd['token']}.calibrated_sensor_token")
            sensor = _lookup(sensors, cs["sensor_token"], self.tables / "calibrated_sensor.json", f"{cs['token']}.sensor_token")
            if sensor["modality"] != "camera":
                continue
            if sensor["channel"] not in images:
                raise InputError(self.tables / "sensor.json", sensor["token"], f"unknown camera {sensor['channel']!r}: expected one of {', '.join(CHANNELS)}")
            images[sensor["channel"]].append(sd)
        for c in CHANNELS:
            if not images[c]:
                raise InputError(sd_path, scene["name"], f"no {'' if sweeps else 'keyframe '}image of camera {c} in the scene")
            images[c].sort(key=lambda sd: sd["timestamp"])
        if sweeps:
            frames = _nearest_frames(images)
        else:
            key = {c: {sd["sample_token"]: sd for sd in images[c]} for c in CHANNELS}
            frames = [[key[c].get(s["token"]) for c in CHANNELS] for s in samples]
        total = len(frames) if not sweeps else len(images[REFERENCE])
        frames = [f for f in frames if all(sd is not None for sd in f)]
        if not frames:
            raise InputError(sd_path, scene["name"], "no frame has an image from all six cameras")
        if len(frames) < total:
            warn(sd_path, f"dropped {total - len(frames)} of {total} frames of {scene['name']} that lack an image of one of the cameras")
        return frames

    def _read_frames(self, frames: list[list[dict]]) -> None:
        poses = _by_token(read_table(self.tables, "ego_pose"))
        ep_path, cs_path = self.tables / "ego_pose.json", self.tables / "calibrated_sensor.json"
        ref = CHANNELS.index(REFERENCE)
        self.image_timestamps = np.array([[sd["timestamp"] for sd in f] for f in frames], dtype=np.float64) * 1e-6
        self.timestamps = self.image_timestamps[:, ref].copy()
        if np.any(np.diff(self.timestamps) <= 0):
            raise InputError(self.tables / "sample_data.json", REFERENCE, "image timestamps must increase along the scene")
        self.image_poses = np.array([[_transform(_lookup(poses, sd["ego_pose_token"], ep_path, sd["token"]), ep_path, sd["ego_pose_token"]) for sd in f] for f in frames])
        self.groundtruth = Trajectory(self.timestamps.copy(), self.image_poses[:, ref].copy())
        self.sync_error = np.linalg.norm(self.image_poses[:, :, :3, 3] - self.image_poses[:, ref, None, :3, 3], axis=-1).max(axis=1)
        self.rig = Rig([self._camera(c, [f[i] for f in frames], cs_path) for i, c in enumerate(CHANNELS)])
        self._files = [[self.root / sd["filename"] for sd in f] for f in frames]
        missing = [p for f in self._files for p in f if not p.is_file()]
        if missing:
            raise InputError(missing[0], None, f"image file is missing ({len(missing)} of the scene's {len(frames) * len(CHANNELS)} images are)")
        spread = np.abs(self.image_timestamps - self.timestamps[:, None]).max(axis=1)
        if spread.max() > MAX_SYNC_DT:
            warn(self.tables, f"{self.name}: the cameras of a rig frame are up to {spread.max() * 1e3:.0f} ms apart (median {np.median(spread) * 1e3:.0f} ms); "
                 f"the rig pose ({REFERENCE}'s ego pose) misplaces the others by up to {self.sync_error.max():.2f} m (median {np.median(self.sync_error):.2f} m)")

    def _camera(self, channel: str, records: list[dict], path: Path) -> CameraSpec:
        """The camera of ``channel`` from its calibrated_sensor, the same on every frame."""
        tokens = {sd["calibrated_sensor_token"] for sd in records}
        cs = [self._calibrations[t] for t in sorted(tokens)]
        T = [_transform(c, path, f"{c['token']}") for c in cs]
        K = [np.array(c["camera_intrinsic"], dtype=np.float64) for c in cs]
        if any(k.shape != (3, 3) for k in K):
            raise InputError(path, f"{cs[0]['token']}.camera_intrinsic", f"camera {channel}: expected a 3x3 matrix")
        if any(np.abs(t - T[0]).max() > 1e-9 or np.abs(k - K[0]).max() > 1e-9 for t, k in zip(T, K)):
            raise InputError(path, channel, f"the scene's images of {channel} have {len(cs)} different calibrations; expected one")
        K = K[0]
        if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[0, 1]) > 1e-9 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9:
            raise InputError(path, f"{cs[0]['token']}.camera_intrinsic", f"camera {channel}: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
        w, h = records[0]["width"], records[0]["height"]
        if any((sd["width"], sd["height"]) != (w, h) for sd in records) or not (isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0):
            raise InputError(self.tables / "sample_data.json", channel, f"expected one positive image size for camera {channel}, got {w}x{h} and others")
        return CameraSpec(channel, "pinhole", w, h, (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), (), T[0])

    def load_frame(self, k: int) -> Frame:
        from ..io import read_image

        images = [read_image(p, (c.width, c.height)) for p, c in zip(self._files[k], self.rig.cameras)]
        return Frame(k, float(self.timestamps[k]), images, [None] * len(images))


def _nearest_frames(images: dict) -> list[list]:
    """Sweeps: per CAM_FRONT image, each camera's image nearest in time within ``MAX_SPREAD``
    (each image used once: the nearer CAM_FRONT image keeps it), or None."""
    t_ref = np.array([sd["timestamp"] for sd in images[REFERENCE]], dtype=np.float64) * 1e-6
    frames = [[None] * len(CHANNELS) for _ in t_ref]
    for i, c in enumerate(CHANNELS):
        t = np.array([sd["timestamp"] for sd in images[c]], dtype=np.float64) * 1e-6
        j = nearest_timestamps(t_ref, t, MAX_SPREAD)
        best = {}
        for k in np.nonzero(j >= 0)[0]:
            if j[k] not in best or abs(t[j[k]] - t_ref[k]) < abs(t[j[k]] - t_ref[best[j[k]]]):
                best[j[k]] = k
        for jj, k in best.items():
            frames[k][i] = images[c][jj]
    return frames


def _listing(names: list[str]) -> str:
    shown = ", ".join(names[:LISTED_SCENES])
    return shown + (f", ... ({len(names)} in all)" if len(names) > LISTED_SCENES else "") if names else "none"
