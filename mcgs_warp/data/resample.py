"""Processing resolution: a sequence resampled so that its widest camera is at most
``max_width`` pixels wide, intrinsics scaled to match.

Real rigs come at 752x480 (EuRoC), 1241x376 (KITTI) or more; the pipeline's cost grows
with the pixel count while its accuracy is set by the geometry (baseline, depth, motion),
so tracking and mapping run on resampled images and every pixel-unit setting is taken
relative to the processing resolution. One factor for the whole rig keeps the cameras'
relative sizes. Pixel centres follow OpenCV (centre of column u at u), so a principal point
maps as ``c' = (c + 0.5) s - 0.5``; distortion coefficients act on normalized coordinates
and stay as they are. Colour is area-averaged; depth takes the nearest sample (an average
across a depth edge would invent a surface).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..rig import CameraSpec, Rig
from .sequence import Frame, Sequence


def resampled_camera(spec: CameraSpec, width: int, height: int) -> CameraSpec:
    """``spec`` at ``width`` x ``height`` pixels (same field of view)."""
    sx, sy = width / spec.width, height / spec.height
    intr = None
    if spec.intrinsics is not None:
        fx, fy, cx, cy = spec.intrinsics
        intr = (fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5)
    return replace(spec, width=int(width), height=int(height), intrinsics=intr, T_b_c=spec.T_b_c.copy())


def processing_scale(rig: Rig, max_width: int) -> float:
    """The factor (<= 1) that brings the rig's widest camera to at most ``max_width`` px
    (``0``: native resolution)."""
    widest = max(c.width for c in rig.cameras)
    return 1.0 if max_width <= 0 or widest <= max_width else max_width / widest


class Resampled(Sequence):
    """``seq`` at ``scale`` times its resolution (rounded per camera); ground truth unchanged."""

    def __init__(self, seq: Sequence, scale: float):
        if not 0 < scale <= 1:
            raise ValueError(f"scale: expected a factor in (0, 1], got {scale}")
        self.seq, self.scale = seq, scale
        self.rig = Rig([resampled_camera(c, max(1, round(c.width * scale)), max(1, round(c.height * scale))) for c in seq.rig.cameras])
        self.timestamps, self.groundtruth, self.name = seq.timestamps, seq.groundtruth, seq.name
        self.depth_exact = seq.depth_exact
        self.gravity = seq.gravity

    def _colour(self, images):
        import cv2

        return [np.ascontiguousarray(cv2.resize(img, (c.width, c.height), interpolation=cv2.INTER_AREA)) for img, c in zip(images, self.rig.cameras)]

    def _depth(self, depths):
        import cv2

        return [None if d is None else cv2.resize(d, (c.width, c.height), interpolation=cv2.INTER_NEAREST) for d, c in zip(depths, self.rig.cameras)]

    def load_frame(self, k: int) -> Frame:
        f = self.seq[k]
        return Frame(f.index, f.timestamp, self._colour(f.images), self._depth(f.depths))

    def depth_cameras(self) -> list[bool]:
        return self.seq.depth_cameras()

    def gt_depths(self, k: int) -> list | None:
        d = self.seq.gt_depths(k)
        return None if d is None else self._depth(d)


def at_processing_resolution(seq: Sequence, max_width: int) -> Sequence:
    """``seq`` itself when its widest camera fits ``max_width``, else :class:`Resampled`."""
    s = processing_scale(seq.rig, max_width)
    return seq if s >= 1.0 else Resampled(seq, s)
