"""Keypoint tracking: each new rig frame's pose from its keypoints matched against keyframes.

The stage that anchors a new keyframe before MCBA (ORB-SLAM's "track reference keyframe",
here for a whole rig): keypoints of every view (:mod:`.keypoints`), matched (mutual, ratio
test) against the keypoints of recent keyframes in the same camera and in the cameras that
overlap it, whose 3D points come from sensor depth or rig stereo at detection, or else from
the keyframe's solved depth where correspondences measured it; then one multi-camera PnP
(:mod:`.pnp`) with the constant-velocity guess as one more RANSAC hypothesis. The same call
relocalizes a lost keyframe against any keyframes (no guess).

Inputs: the rig, which camera pairs overlap, and per call the keypoints it matches against
(``known``: keyframe or frame -> its views, kept by the caller), their poses and a depth lookup.
It holds no state of a run: the keypoint odometry (every frame) and the tracker's keyframe step
share one instance, each with its own store of views.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..rig import Rig
from .keypoints import KeypointDetector, ViewKeypoints, mutual_matches
from .pnp import PnPResult, RigObservations, RigPnP


@dataclass
class KeypointConfig:
    features: int = 1000  # SIFT keypoints per view
    ratio: float = 0.8  # Lowe's ratio test (nearest / second nearest descriptor distance)
    inlier_rad: float = 0.004  # rad: PnP inlier threshold, as an angle between bearings (about 1.5 px at KITTI's 640 px, 0.7 px on 320 px synthetic views)
    min_inliers: int = 20  # a PnP pose with fewer inliers is no pose
    min_inlier_ratio: float = 0.25  # ... and so is one explaining less than this share of the matches
    keyframes: int = 3  # match a new keyframe against this many recent keyframes
    stereo_overlap: float = 0.5  # two cameras that each see at least this share of the other's view are a stereo pair: the second measures depth only, not motion (:attr:`KeypointTracker.observers`; above 1: every camera measures motion)


def motion_observers(n_cameras: int, overlap, stereo_pairs, min_overlap: float) -> list:
    """The cameras whose keypoints measure the rig's motion: all but the second camera of each
    stereo pair. The rig's cameras pair up in order (a camera with the first later one of
    ``stereo_pairs`` that each see at least ``min_overlap`` of the other's view, [C,C]
    ``overlap``; each camera in one pair at most); a pair's second camera gives its partner's
    keypoints their depth and is not itself matched over time, as a stereo keypoint of
    ORB-SLAM2 or of a classical stereo VO is (the right image's coordinate is a depth
    measurement). The two cameras of a pair whose exposures are centred a few milliseconds
    apart (unequal exposure times) disagree on the motion: the second camera's own matches
    over time made a synthetic stereo path with a 3 ms late right camera 0.7 % long at
    10 m/s (tests/ba/test_keypoint_odometry.py)."""
    pairs = {(min(a, b), max(a, b)) for a, b in stereo_pairs}
    second: set = set()
    for a in range(n_cameras):
        if a in second or overlap is None:
            continue
        for b in range(a + 1, n_cameras):
            if b not in second and (a, b) in pairs and min(overlap[a, b], overlap[b, a]) >= min_overlap:
                second.add(b)
                break
    return [c for c in range(n_cameras) if c not in second]


class KeypointTracker:
    def __init__(self, rig: Rig, overlap: np.ndarray | None = None, stereo_pairs=(), config: KeypointConfig | None = None, seed: int = 0):
        """``overlap`` [C,C] (view overlap of the rig's cameras, :func:`camera_overlap`) says
        which cameras a view is matched against besides its own; ``stereo_pairs`` (a, b) are
        triangulated at detection."""
        self.cfg = cfg = config or KeypointConfig()
        self.rig = rig
        C = len(rig)
        self.partners = [[c] + [d for d in range(C) if d != c and overlap is not None and overlap[c, d] > 0] for c in range(C)]
        self.observers = motion_observers(C, overlap, stereo_pairs, cfg.stereo_overlap)
        self.detector = KeypointDetector(rig, stereo_pairs, features=cfg.features, ratio=cfg.ratio)
        self.pnp = RigPnP(rig, inlier_rad=cfg.inlier_rad, seed=seed)

    def detect(self, images, depths=None) -> list[ViewKeypoints]:
        return self.detector.detect(images, depths)

    def points_w(self, k: int, views: list[ViewKeypoints], T_w_b: np.ndarray, depth_at=None, solved=None) -> list[np.ndarray]:
        """World points [M,3] (NaN where unknown) of keyframe ``k``'s keypoints ``views`` per camera:
        ``solved(k, c)`` -> [M,3] world points of their tracks as MCBA last solved them,
        else their own depth (sensor, stereo), else ``depth_at(k, c, uv)`` -> depth [M] (m, 0 =
        unmeasured), the keyframe's solved depth."""
        out = []
        for c, v in enumerate(views):
            P = v.points.copy()
            if depth_at is not None and len(v):
                free = ~v.has_depth
                if free.any():
                    z = depth_at(k, c, v.uv[free])
                    P[free] = np.where((z > 0)[:, None], v.rays[free] * z[:, None], np.nan)
            T = T_w_b @ self.rig.cameras[c].T_b_c
            X = P @ T[:3, :3].T + T[:3, 3]
            if solved is not None and len(v):
                S = solved(k, c)
                X = np.where(np.isfinite(S[:, :1]), S, X)
            out.append(X)
        return out

    def observations(self, views: list[ViewKeypoints], known: dict, keyframes, poses: np.ndarray, depth_at=None, solved=None, cameras=None):
        """2D-3D matches of ``views`` (a new frame) against ``keyframes`` (their keypoints
        ``known[k]``, their rig poses ``poses`` [K,4,4] indexed by keyframe), one set per camera of the new frame (of
        ``cameras``, default all), and per set the matched keypoints ``(keyframe, camera, index
        there, index here)`` [M,4]."""
        obs, pairs, pts_of = [], [], {}  # pts_of: keyframe -> its world points per camera (once per call)
        for c, v in enumerate(views):
            if cameras is not None and c not in cameras:
                continue
            b, X, who = [], [], []
            for k in keyframes:
                if k not in known:
                    continue
                if k not in pts_of:
                    pts_of[k] = self.points_w(k, known[k], poses[k], depth_at, solved)
                pts = pts_of[k]
                for d in self.partners[c]:
                    kv = known[k][d]
                    ok = np.isfinite(pts[d][:, 0])
                    if ok.sum() < 3 or len(v) < 3:
                        continue
                    idx = np.nonzero(ok)[0]
                    m = mutual_matches(v.desc, kv.desc[idx], self.cfg.ratio)
                    b.append(v.bearings[m[:, 0]])
                    X.append(pts[d][idx[m[:, 1]]])
                    who.append(np.stack([np.full(len(m), k), np.full(len(m), d), idx[m[:, 1]], m[:, 0]], 1))
            if sum(len(x) for x in b):  # a camera without matches has no set (PnP's sets and these pairs stay aligned)
                obs.append(RigObservations(c, np.concatenate(b), np.concatenate(X)))
                pairs.append(np.concatenate(who))
        return obs, pairs

    def localize(self, views, known: dict, keyframes, poses, depth_at=None, guess=None, solved=None) -> PnPResult | None:
        """The rig pose of a frame with keypoints ``views`` from matches against
        ``keyframes`` (their keypoints ``known[k]``); None when no pose has enough support (``min_inliers`` and
        ``min_inlier_ratio``). The keypoints of the :attr:`observers` measure the pose; where
        they find none, those of every camera. ``guess`` (constant velocity) competes as a hypothesis;
        ``depth_at`` and ``solved`` give keypoints their 3D points (:meth:`points_w`). The
        result's ``matches`` [M,5] are its inlier matches ``(keyframe, camera there, index
        there, camera here, index here)`` (:class:`~mcgs_warp.ba.keypoint_tracks.KeypointTracks` links them)."""
        for cameras in [self.observers, None] if len(self.observers) < len(views) else [None]:
            obs, pairs = self.observations(views, known, keyframes, poses, depth_at, solved, cameras)
            res = self.pnp.solve(obs, guess=guess, min_inliers=self.cfg.min_inliers)
            if res is not None and res.inlier_ratio >= self.cfg.min_inlier_ratio:
                break
        else:
            return None
        rows = [np.concatenate([p[m][:, :3], np.full((int(m.sum()), 1), o.camera), p[m][:, 3:4]], 1) for o, p, m in zip(obs, pairs, res.inliers)]
        res.matches = np.concatenate(rows).astype(np.int64) if rows else np.zeros((0, 5), np.int64)
        return res
