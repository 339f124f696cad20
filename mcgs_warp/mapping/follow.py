"""How the map follows tracking: the updates the tracker emits (:meth:`~mcgs_warp.system.tracker.Tracker.take_update`)
and the per-pixel depth ratio that moves a keyframe's Gaussians with its depth (paper eq. 13)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PosesMoved:
    """Keyframe rig poses ``T_w_b`` [K,4,4] before and after a solve: anchored Gaussians follow."""

    before: np.ndarray
    after: np.ndarray


@dataclass
class DepthMoved:
    """Keyframe ``k``'s new grid depth [C,h,w] (m, 0 = unknown) at rig pose ``T_w_b``, and its
    full-resolution mapping depth targets (per camera [H,W] m) that follow from it."""

    k: int
    T_w_b: np.ndarray
    depth: np.ndarray
    targets: list


def depth_ratio(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Per-pixel ``new / old`` [C,h,w] of two grid depths (1 where either is unknown),
    3x3-median filtered (one noisy pixel moves no Gaussian) and clipped to [0.5, 2]."""
    import cv2

    ok = (old > 0) & (new > 0)
    r = np.where(ok, new / np.where(ok, old, 1.0), 1.0).astype(np.float32)
    return np.clip(np.stack([cv2.medianBlur(x, 3) for x in r]), 0.5, 2.0)
