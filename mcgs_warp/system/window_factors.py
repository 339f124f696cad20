"""The tracker's MCBA factors besides correspondences and keypoint tracks
(:meth:`~mcgs_warp.system.tracker.Tracker.solve`): sensor-depth alignment between the window's
keyframes (exact sensor depth only) and the keypoint odometry's motion between consecutive
keyframes (:class:`~mcgs_warp.ba.pose_factors.RelativePoseFactors`).

Inputs: the keyframe buffer (poses' frames, sensor depth, grid rays), the rig, the tracking
settings (``depth_weight``, ``odometry_weight``), the keypoint odometry and MCBA's robust
width. State: the last solve's depth-alignment factors (:attr:`WindowFactors.geometric`),
which the health check counts as confident matches.
"""

from __future__ import annotations

from functools import reduce

import numpy as np


class WindowFactors:
    """Geometric factors of a window solve (module docstring). ``exact_depth``: the run has
    exact sensor depth; ``own_depth``: keypoints have depth of their own (sensor depth or rig
    stereo); ``mcba``: the online MCBA, whose ``cfg.huber_delta`` the depth factors share."""

    def __init__(self, buffer, rig, config, odometry, exact_depth: bool, own_depth: bool, mcba):
        self.buf = buffer
        self.T_b_c = np.stack([c.T_b_c for c in rig.cameras])  # [C,4,4] camera -> body
        self.cfg = config  # the run's tracking section
        self.odometry = odometry
        self.exact_depth = exact_depth
        self.own_depth = own_depth
        self.mcba = mcba
        self.geometric = None  # the last solve's depth-alignment factors (window, factors)
        self.grid = None  # grid rays and cameras for them, made once

    def __call__(self, keyframes, edges) -> list:
        """Both kinds for a solve over ``keyframes`` on ``edges`` [E,5]."""
        return self.depth(keyframes, edges) + self.odometry_steps(keyframes)

    def depth(self, keyframes, edges) -> list:
        """Sensor-depth alignment over the window's edges between keyframes (exact sensor
        depth only, ``tracking.depth_weight`` > 0); kept for the health check."""
        from ..ba.depth_factors import DepthAlignmentFactors

        w = self.cfg.depth_weight
        self.geometric = None
        if not self.exact_depth or w <= 0:
            return []
        keyframes = list(keyframes)
        slot = {k: s for s, k in enumerate(keyframes)}
        pairs = np.array([(slot[i], ci, slot[j], cj) for i, ci, j, cj in np.asarray(edges)[:, :4].tolist() if i != j], int).reshape(-1, 4)
        if not len(pairs):
            return []
        buf = self.buf
        if self.grid is None:
            self.grid = (buf.rays.numpy().astype(np.float64), [c.warp_camera() for c in buf.reduced])
        depth = buf.depth_prior.numpy()[keyframes]
        f = DepthAlignmentFactors(pairs, depth, *self.grid, self.T_b_c, w, self.mcba.cfg.huber_delta)
        self.geometric = (keyframes, f)
        return [f]

    def odometry_steps(self, keyframes) -> list:
        """The keypoint odometry's motion between consecutive keyframes of ``keyframes``
        where it placed every frame between them (PnP or a two-view step), weighted by its
        information times ``tracking.odometry_weight``
        (:class:`~mcgs_warp.ba.pose_factors.RelativePoseFactors`). PnP steps count only where
        keypoints have depth of their own (sensor depth or rig stereo): on a rig without either
        (front + back cameras, a mono prior) PnP placed its points on this system's solved
        depth, and as a factor it pulled the window's scale 4 % off (0.6 cm -> 2.5 cm on 1.7 m,
        tests/system/test_rgb_only.py). Two-view steps take their length from the rig's lever
        arms, not from any depth, so they count on every rig: on the 6-camera surround drive at
        2 Hz, whose dense solves pass the health check with 0.1-89x steps, they hold the
        trajectory (seeds 11-13: 1.74 / 165 / 2.21 m -> 0.23 / 0.25 / 1.18 m)."""
        from ..ba.pose_factors import RelativePoseFactors

        w, odo = self.cfg.odometry_weight, self.odometry
        if odo is None or w <= 0:
            return []
        own_depth = self.own_depth
        keyframes = list(keyframes)
        pairs, motions, info = [], [], []
        for s in range(1, len(keyframes)):
            fa, fb = int(self.buf.frame_index[keyframes[s - 1]]), int(self.buf.frame_index[keyframes[s]])
            span = odo.span(fa, fb)
            two_view = all(f in odo.two_view for f in span)
            if not odo.span_tracked(fa, fb) or not (own_depth or two_view):
                continue
            cov = odo.relative_covariance(fa, fb)
            try:
                lam = np.linalg.inv(cov)
            except np.linalg.LinAlgError:
                continue
            if not np.all(np.isfinite(lam)):
                continue
            pairs.append((s - 1, s))
            # without the rig's own depth the window's PnP links stood on this system's depth:
            # the measured two-view steps themselves
            motions.append(odo.relative(fa, fb) if own_depth else reduce(np.matmul, [odo.two_view[f] for f in span]))
            info.append(w * 0.5 * (lam + lam.T))
        return [RelativePoseFactors(pairs, motions, info)] if pairs else []
