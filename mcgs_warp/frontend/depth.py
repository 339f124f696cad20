"""Depth priors per keyframe view, behind a small interface.

A :class:`DepthPrior` gives, for a frame, one full-resolution depth map per camera
(m, camera-model depth, 0 = unknown) or ``None`` where it has nothing. MCBA uses the
prior sampled on the reduced grid (:func:`grid_depth`) both to initialize inverse
depth and, JDSA-scaled, as a soft prior.

* :class:`SensorDepth` — the dataset's depth (RGB-D, synthetic): metric and exact, so
  JDSA leaves it unscaled.
* :class:`ConstantDepth` — no depth sensor: a constant initial depth, as DROID-SLAM
  starts from; the scale then comes from cross-view edges (known baselines).
* a monocular network (the paper's Metric3D) would be a third implementation (metric,
  not exact: JDSA rescales it); none is bundled because nothing may download weights
  at run time.
"""

from __future__ import annotations

import numpy as np

from ..buffer import grid_pixels


class DepthPrior:
    #: whether the prior is trusted as a soft constraint (else only an initial value)
    metric: bool = False
    #: whether it is exact up to noise (sensor depth): then JDSA must not rescale it, or
    #: the scale grids would follow MCBA's depths and free the metric scale
    exact: bool = False

    def __call__(self, frame, rig) -> list:
        raise NotImplementedError


class SensorDepth(DepthPrior):
    metric = True
    exact = True

    def __call__(self, frame, rig) -> list:
        return list(frame.depths)


class ConstantDepth(DepthPrior):
    def __init__(self, depth: float = 3.0):
        self.depth = depth

    def __call__(self, frame, rig) -> list:
        return [np.full((c.height, c.width), self.depth, np.float32) for c in rig.cameras]


def default_prior(sequence) -> DepthPrior:
    """Sensor depth when the first frame has any, else a constant initialization."""
    first = sequence[0]
    return SensorDepth() if any(d is not None for d in first.depths) else ConstantDepth()


def grid_depth(depths, rig, stride: int, shape) -> np.ndarray:
    """Depth maps sampled on the reduced grid: [C,h,w] (0 where unknown)."""
    out = np.zeros((len(rig),) + tuple(shape), np.float32)
    for c, (spec, d) in enumerate(zip(rig.cameras, depths)):
        if d is None:
            continue
        uv = grid_pixels(spec, stride).astype(int)
        g = d[uv[..., 1], uv[..., 0]]
        out[c, : g.shape[0], : g.shape[1]] = np.where(np.isfinite(g) & (g > 0), g, 0.0)
    return out
