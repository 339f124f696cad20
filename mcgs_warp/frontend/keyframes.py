"""Keyframe selection by mean optical-flow magnitude (paper §III-A1).

A frame becomes a keyframe when the mean flow magnitude from the last keyframe,
averaged over the rig's cameras, exceeds ``threshold`` pixels (measured on images
downscaled by ``scale`` for speed, reported in full-resolution pixels).
"""

from __future__ import annotations

import numpy as np

#: Default keyframe threshold (full-resolution px of mean flow), the tuned value the system
#: runs with (``mcgs_warp.system.config.TrackingConfig.keyframe_flow_px`` takes it from here).
THRESHOLD_PX = 10.0


class KeyframeSelector:
    def __init__(self, flow, threshold: float = THRESHOLD_PX, scale: float = 0.5):
        self.flow = flow  # an object with .flow(image_a, image_b) -> (flow [H,W,2], confidence [H,W])
        self.threshold = threshold
        self.scale = scale

    def mean_flow(self, images_a, images_b) -> float:
        """Mean flow magnitude (full-resolution px) from ``images_a`` to ``images_b`` over all cameras."""
        import cv2

        mags = []
        for a, b in zip(images_a, images_b):
            if self.scale != 1.0:
                a = cv2.resize(a, None, fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA)
                b = cv2.resize(b, None, fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA)
            f, _ = self.flow.flow(a, b)
            mags.append(float(np.linalg.norm(f, axis=-1).mean()) / self.scale)
        return float(np.mean(mags))

    def is_keyframe(self, last_keyframe_images, images) -> tuple[bool, float]:
        m = self.mean_flow(last_keyframe_images, images)
        return m > self.threshold, m
