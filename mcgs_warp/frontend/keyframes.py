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
        self._previous, self._previous_key = None, None  # the last frame's flows, and which keyframe they start at

    def flows(self, images_a, images_b) -> list:
        """Flow fields [C] ([h,w,2] in rad of view angle, at ``scale``) from ``images_a`` to ``images_b``."""
        import cv2

        out = []
        for a, b, focal in zip(images_a, images_b, self.focal):
            if self.scale != 1.0:
                a = cv2.resize(a, None, fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA)
                b = cv2.resize(b, None, fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA)
            f, _ = self.flow.flow(a, b)
            out.append(f / self.scale / focal)
        return out

    def mean_flow(self, images_a, images_b) -> float:
        """Mean flow magnitude (rad of view angle) from ``images_a`` to ``images_b`` over all cameras."""
        return float(np.mean([np.linalg.norm(f, axis=-1).mean() for f in self.flows(images_a, images_b)]))

    def is_keyframe(self, last_keyframe_images, images) -> tuple[bool, float]:
        """Whether ``images`` make a keyframe, and the image motion (rad) since the frame
        before (:meth:`motion`; the whole flow for the first frame after a keyframe)."""
        flows = self.flows(last_keyframe_images, images)
        m = float(np.mean([np.linalg.norm(f, axis=-1).mean() for f in flows]))
        previous = self._previous if self._previous is not None and self._previous_key is last_keyframe_images else None
        self._previous, self._previous_key = flows, last_keyframe_images
        return m >= self.threshold, motion(flows, previous)  # a threshold of 0 makes every frame a keyframe


def motion(flows, previous=None, q: float = 75.0) -> float:
    """Image motion (rad) between two frames seen from one keyframe: per camera the ``q``-th
    percentile over pixels of the change of flow ``flows`` [C] ([h,w,2], rad) against
    ``previous`` (the frame before's flows from the same keyframe; None: that frame is the
    keyframe, zero flow), averaged over cameras. A field difference, not a difference of mean
    magnitudes (which rotation and parallax can hold constant while the rig moves): a pause is
    a pause in the images. An upper percentile, because a car's far field barely moves."""
    prev = [None] * len(flows) if previous is None else previous
    return float(np.mean([np.percentile(np.linalg.norm(f if p is None else f - p, axis=-1), q) for f, p in zip(flows, prev)]))
