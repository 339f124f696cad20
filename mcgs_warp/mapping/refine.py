"""Offline refinement (paper §III-C), after the online loop and global bundle adjustment
(:meth:`mcgs_warp.system.slam.SLAM.refine`: MCBA over every keyframe on the factor graph,
with long and loop edges): joint refinement of the map, the keyframe rig poses and the
per-image affine exposures through the renderer.
"""

from __future__ import annotations

import numpy as np

from .mapper import Mapper


def joint_refinement(mapper: Mapper, iterations: int, poses: bool = True, exposure: bool = True, progress=None):
    """Optimize map, rig poses (all but the first keyframe) and exposures together. The map
    is densified in the first half only (as 3DGS densifies until half its iterations):
    Gaussians cloned or split near the end would reach the output unoptimized (a densify
    at the last step of a fit costs 1-3 dB on tests/mapping's fixture)."""
    mapper.optimize_poses, mapper.optimize_exposure = poses, exposure
    half = iterations // 2
    try:
        results = mapper.optimize(half, progress=progress)
        report = None if progress is None else (lambda it, r: progress(half + it, r))
        return results + mapper.optimize(iterations - half, progress=report, densify=False)
    finally:
        mapper.optimize_poses = mapper.optimize_exposure = False


def exposure_gains(mapper: Mapper) -> np.ndarray:
    """Per-image affine exposure ``(a, b)`` [K,C,2] of the registered keyframes."""
    e = mapper.buf.exposure.numpy()[: len(mapper.buf)].astype(np.float64)
    e[..., 0] = np.exp(e[..., 0])
    return e
