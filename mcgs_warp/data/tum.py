"""TUM RGB-D dataset reader: one RGB-D camera as a 1-camera rig.

Layout: ``rgb.txt`` and ``depth.txt`` ('timestamp filename' lines, '#' comments),
``rgb/``, ``depth/`` (16-bit PNG, 5000 units per metre), optional
``groundtruth.txt`` (TUM trajectory of the camera, so ``T_b_c = I``). Depth frames
are associated with the nearest RGB timestamp within 20 ms (as TUM's associate.py); an RGB
frame without one has no depth pixel (all 0 = unknown, as a sensor dropout), so the mode of
the run (RGB-D or not) never depends on which frames happen to have depth. A ``rig.yaml``
``time_offset`` (camera clock = rig clock + offset) moves the frames onto the rig clock of
the ground truth.

Calibration: a ``rig.yaml`` in the folder (or passed in), else the published
calibration of the Freiburg 1/2/3 sensor named in the folder name.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError, warn
from ..rig import CameraSpec, Rig, load_rig
from .sequence import MAX_UNMATCHED_FRACTION, Frame, Sequence
from .trajectory import MAX_ASSOCIATION_DT, nearest_timestamps, read_tum

DEPTH_SCALE = 5000.0  # TUM depth PNG units per metre

# Published calibrations (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).
FREIBURG = {
    "freiburg1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": ((535.4, 539.2, 320.1, 247.6), ()),
}


def read_file_list(path: Path):
    """``(timestamps [K], filenames [K])`` of a TUM list file."""
    if not path.is_file():
        raise InputError(path, None, "file not found")
    stamps, names = [], []
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < 2:
            raise InputError(path, f"line {lineno}", f"expected 'timestamp filename', got {line!r}")
        try:
            t = float(parts[0])
        except ValueError:
            raise InputError(path, f"line {lineno}", f"expected a timestamp, got {parts[0]!r}") from None
        if not np.isfinite(t) or (stamps and t <= stamps[-1]):
            raise InputError(path, f"line {lineno}", "timestamps must be finite and increasing")
        stamps.append(t)
        names.append(parts[1])
    if not stamps:
        raise InputError(path, None, "no entries")
    return np.array(stamps), names


def associate(t_a: np.ndarray, t_b: np.ndarray, max_dt: float = MAX_ASSOCIATION_DT) -> np.ndarray:
    """Depth frame index per RGB timestamp (nearest within ``max_dt``), or -1."""
    return nearest_timestamps(t_a, t_b, max_dt)


class TumSequence(Sequence):
    def __init__(self, path, rig: Rig | None = None):
        self.root = Path(path)
        self.name = self.root.name
        self.rig = self._rig() if rig is None else rig
        camera_stamps, self._rgb = read_file_list(self.root / "rgb.txt")
        self.timestamps = camera_stamps - self.rig.cameras[0].time_offset  # rig clock
        self._depth = [None] * len(self.timestamps)
        self.has_depth = False
        if (self.root / "depth.txt").is_file():
            t_d, names = read_file_list(self.root / "depth.txt")
            match = associate(camera_stamps, t_d)  # both on the sensor's clock
            for k, j in enumerate(match):
                if j >= 0:
                    self._depth[k] = names[j]
            unmatched = int(np.count_nonzero(match < 0))
            self.has_depth = unmatched < len(match)
            if not self.has_depth:
                warn(self.root / "depth.txt", f"no rgb frame (rgb.txt) has a depth frame within {MAX_ASSOCIATION_DT} s: the run has no depth")
            elif unmatched > MAX_UNMATCHED_FRACTION * len(match):
                warn(
                    self.root / "depth.txt",
                    f"{unmatched} of {len(match)} rgb frames (rgb.txt) have no depth frame within {MAX_ASSOCIATION_DT} s; those frames have no depth pixel (0 = unknown)",
                )
        gt = self.root / "groundtruth.txt"
        self.groundtruth = read_tum(gt) if gt.is_file() else None

    def _rig(self) -> Rig:
        if (self.root / "rig.yaml").is_file():
            return load_rig(self.root / "rig.yaml")
        for key, (intr, dist) in FREIBURG.items():
            if key in self.root.name:
                return Rig([CameraSpec("rgb", "pinhole", 640, 480, intr, dist)])
        raise InputError(self.root, "rig.yaml", "missing calibration: add rig.yaml or use a folder named after freiburg1/2/3")

    def load_frame(self, k: int) -> Frame:
        from ..io import read_image

        cam = self.rig.cameras[0]
        size = (cam.width, cam.height)
        image = read_image(self.root / self._rgb[k], size)
        depth = None
        if self._depth[k] is not None:
            depth = read_image(self.root / self._depth[k], size, depth=True).astype(np.float32) / DEPTH_SCALE
        elif self.has_depth:
            depth = np.zeros((cam.height, cam.width), np.float32)  # a dropout: no depth pixel
        return Frame(k, float(self.timestamps[k]), [image], [depth])

    def depth_cameras(self) -> list[bool]:
        return [self.has_depth]
