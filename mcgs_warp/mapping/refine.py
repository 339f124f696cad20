"""Offline global refinement (paper §III-C), after the online loop.

1. Global bundle adjustment: MCBA over all keyframes (temporal and cross-view edges
   from the flow front end), first keyframe fixed; the map follows the keyframes
   (eq. 12).
2. Joint refinement of the map, the keyframe rig poses and the per-image affine
   exposures through the renderer.
"""

from __future__ import annotations

import numpy as np

from ..ba.graph import build_edges, camera_overlap
from ..ba.mcba import MCBA, MCBAConfig, MCBAStats
from .mapper import Mapper


def global_bundle_adjustment(mapper: Mapper, flow, config: MCBAConfig | None = None, radius: int = 2) -> MCBAStats:
    """MCBA over every keyframe of the mapper's buffer; anchored Gaussians follow."""
    buf = mapper.buf
    edges = build_edges(range(len(buf)), len(buf.rig), camera_overlap(buf.rig, stride=buf.stride), radius=radius)
    targets, weights = flow.correspondences(buf, edges)
    before = buf.get_poses()
    stats = MCBA(buf, config or MCBAConfig(iterations=5)).solve(edges, targets, weights, keyframes=range(len(buf)))
    mapper.map.follow_keyframes(before, buf.get_poses())
    return stats


def joint_refinement(mapper: Mapper, iterations: int, poses: bool = True, exposure: bool = True, progress=None):
    """Optimize map, rig poses (all but the first keyframe) and exposures together."""
    mapper.optimize_poses, mapper.optimize_exposure = poses, exposure
    try:
        return mapper.optimize(iterations, progress=progress)
    finally:
        mapper.optimize_poses = mapper.optimize_exposure = False


def exposure_gains(mapper: Mapper) -> np.ndarray:
    """Per-image affine exposure ``(a, b)`` [K,C,2] of the registered keyframes."""
    e = mapper.exposure.numpy()[: len(mapper.buf)].astype(np.float64)
    e[..., 0] = np.exp(e[..., 0])
    return e
