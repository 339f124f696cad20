"""Keyframe selection by mean optical-flow magnitude (paper §III-A1).

A frame becomes a keyframe when the mean flow magnitude from the last keyframe,
averaged over the rig's cameras, exceeds ``threshold`` radians of view angle: each
camera's mean flow in its own pixels (measured on images downscaled by ``scale`` for
speed) divided by its pixels per radian (:attr:`~mcgs_warp.rig.CameraSpec.pixels_per_radian`). An angle, not a
pixel count, so one threshold means the same motion at any resolution and field of view
(the built-in 320x240 rig's 10 px at a 180 px focal length is KITTI's 20 px at 640 px wide).
"""

from __future__ import annotations

import numpy as np

#: Default keyframe threshold (rad of mean flow), the tuned value the system runs with
#: (``mcgs_warp.system.config.TrackingConfig.keyframe_flow`` takes it from here): the 10 px
#: tuned on the built-in rig (180 px focal length) until 2026-12-01.
THRESHOLD_RAD = 0.055


class KeyframeSelector:
    def __init__(self, flow, cameras, threshold: float = THRESHOLD_RAD, scale: float = 0.5):
        self.flow = flow  # an object with .flow(image_a, image_b) -> (flow [H,W,2], confidence [H,W])
        self.focal = [spec.pixels_per_radian for spec in cameras]  # the rig's CameraSpecs, in image order
        self.threshold = threshold
        self.scale = scale

    def mean_flow(self, images_a, images_b) -> float:
        """Mean flow magnitude (rad of view angle) from ``images_a`` to ``images_b`` over all cameras."""
        import cv2

        mags = []
        for a, b, focal in zip(images_a, images_b, self.focal):
            if self.scale != 1.0:
                a = cv2.resize(a, None, fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA)
                b = cv2.resize(b, None, fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA)
            f, _ = self.flow.flow(a, b)
            mags.append(float(np.linalg.norm(f, axis=-1).mean()) / self.scale / focal)
        return float(np.mean(mags))

    def is_keyframe(self, last_keyframe_images, images) -> tuple[bool, float]:
        m = self.mean_flow(last_keyframe_images, images)
        return m > self.threshold, m
