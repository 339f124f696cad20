"""How the map follows tracking: the updates the tracker emits (per keyframe one
:class:`KeyframeUpdate`, :meth:`~mcgs_warp.system.tracker.Tracker.add_keyframe`; the moves of a
solve, :meth:`~mcgs_warp.system.tracker.Tracker.take_update`), which the mapper applies
(:meth:`~mcgs_warp.mapping.mapper.Mapper.apply`, :meth:`~mcgs_warp.mapping.mapper.Mapper.follow`),
and the per-pixel depth ratio that moves a keyframe's Gaussians with its depth (paper eq. 13).
As ORB-SLAM3's tracking inserts keyframes into its local mapper's queue: the tracker says what
moved and what to map, and never touches the map."""

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


@dataclass
class Registration:
    """Keyframe ``k`` to register with the map: its full-resolution depth targets (per camera
    [H,W] m, 0 = none) and the grid depth [C,h,w] (m) its Gaussians are placed with."""

    k: int
    targets: list
    placed: np.ndarray


@dataclass
class KeyframeUpdate:
    """What one new keyframe means for the map, in the order the mapper applies it: the pose
    and depth changes of its solve (``moved``: :class:`PosesMoved`, :class:`DepthMoved`), then
    the keyframes to register (``register``: :class:`Registration`, the new one and, at the
    bootstrap, keyframe 0; none that tracking lost). ``keyframe``: the new keyframe's index;
    ``window``: the keyframes of the tracker's sliding window, which mapping iterates over."""

    keyframe: int
    moved: list
    register: list
    window: list


def depth_ratio(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Per-pixel ``new / old`` [C,h,w] of two grid depths (1 where either is unknown),
    3x3-median filtered (one noisy pixel moves no Gaussian) and clipped to [0.5, 2]."""
    import cv2

    ok = (old > 0) & (new > 0)
    r = np.where(ok, new / np.where(ok, old, 1.0), 1.0).astype(np.float32)
    return np.clip(np.stack([cv2.medianBlur(x, 3) for x in r]), 0.5, 2.0)
