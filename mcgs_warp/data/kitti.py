"""KITTI odometry reader: a rectified stereo pair of a sequence folder as a 2-camera rig.

Layout (``sequences/NN/`` of the odometry split, or a folder laid out like one)::

    image_0/000000.png ...   left grey camera (rectified, 8-bit)
    image_1/000000.png ...   right grey camera
    image_2/, image_3/       left / right colour cameras (optional)
    calib.txt                'P0: 12 numbers' ... 'P3:' (3x4 row-major projections), optional 'Tr:'
    times.txt                one time per frame, s
    poses.txt                optional ground truth: one row-major 3x4 T_w_cam0 per frame (m);
                             full KITTI keeps it at ../../poses/NN.txt instead

Every camera is rectified onto the image plane of camera 0, so ``P_i = K_i [I | t_i]`` with
``t_i = K_i^-1 P_i[:, 3]`` the position of camera 0 in camera i's frame. The rig body is
camera 0 (``T_b_c0 = I``), so ground-truth poses are ``T_w_b`` as they stand (KITTI camera
axes: x right, y down, z forward; gravity is about +y). The grey pair is the default; the
colour pair is ``cameras="colour"`` (``mcgs-slam run --kitti-cameras colour``), and all four
cameras, both pairs on one image plane, are ``cameras="all"`` (a 4-camera rig: the colour pair's
longer baseline and the grey pair's measure depth together). Grey images are replicated to RGB. ``Tr:`` (velodyne -> camera 0) is read and ignored.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..rig import CameraSpec, Rig
from .sequence import Frame, Sequence, read_timestamps
from .trajectory import Trajectory

PAIRS = {"grey": (0, 1), "colour": (2, 3), "all": (0, 1, 2, 3)}  # which image_<i> folders form the rig


def is_kitti(path) -> bool:
    path = Path(path)
    return (path / "calib.txt").is_file() and ((path / "image_0").is_dir() or (path / "image_2").is_dir())


def read_calib(path: Path) -> dict:
    """``calib.txt`` as {name: [3,4] array}: every ``NAME: 12 numbers`` line."""
    if not path.is_file():
        raise InputError(path, None, "file not found")
    out = {}
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        name, sep, rest = line.partition(":")
        if not sep:
            raise InputError(path, f"line {lineno}", f"expected 'NAME: 12 numbers', got {line.strip()[:60]!r}")
        try:
            vals = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            raise InputError(path, name.strip(), "expected 12 numbers") from None
        if vals.size != 12 or not np.all(np.isfinite(vals)):
            raise InputError(path, name.strip(), f"expected 12 finite numbers (a row-major 3x4 matrix), got {vals.size}")
        out[name.strip()] = vals.reshape(3, 4)
    return out


def camera_from_projection(src: Path, name: str, P: np.ndarray, size: tuple[int, int]) -> CameraSpec:
    """A rectified camera from its 3x4 projection ``P = K [I | t]``: intrinsics from ``K`` and
    ``T_b_c`` (camera -> body = camera 0) the translation ``-t``."""
    K = P[:, :3]
    if abs(K[1, 0]) > 1e-9 or abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9 or abs(K[2, 2] - 1.0) > 1e-6 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(src, name, f"expected a rectified projection K [I | t] with K upper triangular, K[2,2] = 1 and positive focal lengths, got K = {K.tolist()}")
    t = np.linalg.solve(K, P[:, 3])  # camera 0's origin in this camera's frame
    T_b_c = np.eye(4)
    T_b_c[:3, 3] = -t
    w, h = size
    return CameraSpec(name=name, model="pinhole", width=w, height=h, intrinsics=(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])), T_b_c=T_b_c)


def read_kitti_poses(path: Path, n: int | None = None) -> np.ndarray:
    """``poses.txt``: [K,4,4] ``T_w_cam0`` from one row-major 3x4 matrix per line."""
    rows = []
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        try:
            vals = np.array([float(v) for v in line.split()])
        except ValueError:
            raise InputError(path, f"line {lineno}", "expected 12 numbers") from None
        if vals.size != 12 or not np.all(np.isfinite(vals)):
            raise InputError(path, f"line {lineno}", f"expected 12 finite numbers (a row-major 3x4 pose), got {vals.size}")
        T = np.eye(4)
        T[:3] = vals.reshape(3, 4)
        rows.append(T)
    if n is not None and len(rows) != n:
        raise InputError(path, None, f"lists {len(rows)} poses but times.txt lists {n} frames (one pose per frame expected)")
    return np.array(rows)


def find_poses(root: Path) -> Path | None:
    """``poses.txt`` in the folder, else KITTI's ``../../poses/NN.txt`` for ``sequences/NN``."""
    inside = root / "poses.txt"
    if inside.is_file():
        return inside
    beside = root.parent.parent / "poses" / f"{root.name}.txt"
    return beside if beside.is_file() else None


class KittiSequence(Sequence):
    """A KITTI odometry sequence folder (module docstring); ``cameras``: ``grey``, ``colour`` or ``all``."""

    def __init__(self, path, cameras: str = "grey"):
        from ..io import read_image

        self.root = Path(path)
        self.name = self.root.name
        if cameras not in PAIRS:
            raise InputError(None, "--kitti-cameras", f"expected one of {' | '.join(PAIRS)}, got {cameras!r}")
        calib_path = self.root / "calib.txt"
        calib = read_calib(calib_path)
        self.timestamps = read_timestamps(self.root / "times.txt")
        specs, self._folders = [], []
        for i in PAIRS[cameras]:
            folder = self.root / f"image_{i}"
            if not folder.is_dir():
                hint = {"colour": " (the colour pair needs image_2 and image_3)", "all": " (all four cameras need image_0 to image_3)"}.get(cameras, " (KITTI stereo needs image_0 and image_1; --kitti-cameras colour reads image_2/image_3)")
                raise InputError(folder, None, f"missing image folder{hint}")
            if f"P{i}" not in calib:
                raise InputError(calib_path, f"P{i}", f"missing projection matrix for image_{i}")
            n_files = len(list(folder.glob("*.png")))
            if n_files != len(self.timestamps):
                raise InputError(folder, None, f"holds {n_files} images but times.txt lists {len(self.timestamps)} frames")
            first = folder / f"{0:06d}.png"
            img = read_image(first)
            specs.append(camera_from_projection(calib_path, f"P{i}", calib[f"P{i}"], (img.shape[1], img.shape[0])))
            specs[-1].name = f"image_{i}"
            self._folders.append(folder)
        # the body is camera 0 of KITTI: with the colour pair, P2/P3 carry their offsets from it
        self.rig = Rig(specs)
        self.gravity = np.array([0.0, 1.0, 0.0])  # world = camera 0 at frame 0, y down
        gt = find_poses(self.root)
        self.groundtruth = Trajectory(self.timestamps.copy(), read_kitti_poses(gt, len(self.timestamps))) if gt is not None else None

    def load_frame(self, k: int) -> Frame:
        from ..io import read_image

        images = []
        for folder, c in zip(self._folders, self.rig.cameras):
            path = folder / f"{k:06d}.png"
            images.append(read_image(path, (c.width, c.height)))
        return Frame(k, float(self.timestamps[k]), images, [None] * len(images))
