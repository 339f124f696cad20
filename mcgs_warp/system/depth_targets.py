"""The mapper's depth targets per keyframe (paper eq. 11's depth term; they also seed the
keyframe's Gaussians): exact sensor depth as is; otherwise the tracker's grid depth where
something measured it, sharpened by the JDSA-scaled prior and filled by the keyframe's sweep
depth (:meth:`DepthTargets.compute`).

Inputs: the keyframe buffer (grid depth, prior confidence, JDSA grids, poses, images), the
factor graph's correspondence weights, the depth prior and the rig's sweep stereo; per call,
the keyframe's frame and the keyframes whose poses tracking lost or kept (they are no sweep
sources). State: each keyframe's sweep depth, computed once (:attr:`DepthTargets.sweeps`,
checkpointed). Output: full-resolution depth per camera. The tracker asks for them when the
mapper registers a keyframe and whenever a solve moves a mapped keyframe's depth
(:meth:`DepthTargets.moved`); and for the solved depth at keypoints (:meth:`DepthTargets.solved_at`).
"""

from __future__ import annotations

import numpy as np

from ..ba.graph import FactorGraph
from ..ba.jdsa import scale_field
from ..buffer import KeyframeBuffer
from ..frontend.depth import DepthPrior, upsample_inverse_depth_guided
from ..frontend.stereo import RigStereo, upsample_nearest
from ..mapping.follow import DepthMoved
from ..rig import Rig


class DepthTargets:
    """Full-resolution mapping depth targets per keyframe (module docstring). ``exact``: the
    prior is exact sensor depth, the target as is; ``metric_scale``: the run measures metric
    scale (without it no sweep depth is kept: the scale drifts while kept depth would not);
    ``window``: keyframes on either side of a keyframe that may be its sweep sources."""

    def __init__(self, buffer: KeyframeBuffer, rig: Rig, prior: DepthPrior, stereo: RigStereo, graph: FactorGraph, exact: bool, metric_scale: bool, window: int):
        self.buf = buffer
        self.rig = rig
        self.prior = prior
        self.stereo = stereo
        self.graph = graph
        self.exact = exact
        self.metric_scale = metric_scale
        self.window = window
        self.sweeps: dict = {}  # keyframe -> per camera [h,w] float16 depth (m, 0 none) of its rig-pair and time-baseline sweeps at sweep resolution (:meth:`sweep`)

    def compute(self, frame, k: int, lost, kept, disp=None, weight=None) -> list:
        """Full-resolution depth targets [H,W] per camera (m, 0 = none) of keyframe ``k`` at
        ``frame``: exact sensor depth as is; otherwise the current estimate (grid depth
        ``disp`` [C,h,w] (1/m, default the buffer's) where correspondences (``weight``, default
        :meth:`measured_weight`) or a prior constrain it, upsampled guided by the image, which
        fills up to a grid cell around constrained samples), sharpened by the JDSA-scaled
        prior where the two agree within 10 %, and where neither measured a pixel, the
        keyframe's rig-pair and time-baseline sweep depth (:meth:`sweep`; ``lost``,
        ``kept``: keyframes whose poses tracking did not measure). (Keeping only
        well-measured pixels as targets was tried: far regions then drift further, depth L1
        0.34 -> 0.47 m.)"""
        import cv2

        if self.exact:
            return list(frame.depths)
        buf, s = self.buf, self.buf.stride
        disp = buf.disp.numpy()[k] if disp is None else disp
        constrained = self.constrained(k, self.measured_weight([k])[k] if weight is None else weight)
        depths = self.prior(frame, self.rig) if self.prior.metric else [None] * len(self.rig)
        grids = buf.scales[k].numpy()  # [C,m,n]
        swept = self.sweep(k, frame, lost, kept)
        out = []
        for c, spec in enumerate(self.rig.cameras):
            h, w = spec.height // s, spec.width // s
            full = upsample_inverse_depth_guided(np.where(constrained[c, :h, :w], disp[c, :h, :w], 0.0), spec, s, frame.images[c], device=buf.device)
            if depths[c] is not None:
                # the JDSA field lives on the buffer's grid (buf.h x buf.w), this camera's part [:h,:w]
                field = scale_field(grids[c], buf.h, buf.w)[:h, :w].astype(np.float32)
                scaled = depths[c] * cv2.resize(field, (spec.width, spec.height), interpolation=cv2.INTER_LINEAR)
                agree = (scaled > 0) & (full > 0) & (np.abs(scaled - full) < 0.1 * full)
                full = np.where(agree, scaled, full)
            if swept is not None:
                full = np.where(full > 0, full, upsample_nearest(swept[c], spec, self.stereo.cfg.scale).astype(np.float32))
            out.append(full)
        return out

    def sweep(self, k: int, frame, lost, kept):
        """Keyframe ``k``'s sweep depth, per camera [h,w] at sweep resolution (m, 0 = none),
        or None (no rig pair, no source): :meth:`RigStereo.temporal_depth`, the view swept
        against the same camera at up to ``tracking.stereo.temporal_sources`` keyframes of
        the window at least ``temporal_baseline`` away where that sweep is confident, else
        the rig pairs' depth. Sources: the nearest earlier keyframes whose poses tracking
        measured (neither in ``lost`` nor in ``kept``), else later ones (keyframe 0 is mapped
        after keyframe 1), at the solved poses. Kept (float16, :attr:`sweeps`) once a source
        is there; without one, and for a kept keyframe (its pose may be a prediction), the rig
        pairs' depth alone; None in a run without metric scale (its scale drifts while kept
        depth would not). A side camera's near road at speed or a wall only one camera sees:
        DIS does not match such motion and no rig pair sees it, so the fill guessed its depth;
        and the pairs measure pixels MCBA left unconstrained (street seed 12, RGB only: depth
        L1 1.28 -> 0.72 m with the time sweep, -> 0.67 m with both)."""
        if k in self.sweeps:
            return self.sweeps[k]
        if not self.metric_scale:
            return None
        sc, buf, rig = self.stereo.cfg, self.buf, self.rig
        sources = []
        if sc.temporal_sources > 0 and k not in kept:
            poses = buf.get_poses()
            near = list(range(k - 1, max(k - 1 - self.window, -1), -1)) + list(range(k + 1, min(k + 1 + self.window, len(buf))))
            unverified = set(lost) | set(kept)
            sources = [j for j in near if j not in unverified and np.linalg.norm(poses[j][:3, 3] - poses[k][:3, 3]) >= sc.temporal_baseline][: sc.temporal_sources]
        if not sources and not self.stereo.pairs:
            return None
        views = [[] for _ in range(len(rig))]
        for j in sources:
            for c, spec in enumerate(rig.cameras):
                views[c].append((buf.image(j, c), np.linalg.inv(poses[j] @ spec.T_b_c) @ poses[k] @ spec.T_b_c))
        depth = self.stereo.temporal_depth(frame.index, frame.images, views)
        if sources:
            self.sweeps[k] = depth = [d.astype(np.float16) for d in depth]
        return depth

    def measured_weight(self, keyframes) -> dict:
        """Per keyframe [C,h,w]: summed correspondence confidence of every edge (active or
        stored) leaving each of its grid pixels (:meth:`FactorGraph.measured_weight`)."""
        return {k: self.graph.measured_weight(k, len(self.rig)) for k in set(keyframes)}

    def constrained(self, k: int, weight: np.ndarray) -> np.ndarray:
        """[C,h,w] bool: grid pixels of keyframe k whose depth something measured (confident
        correspondences from the view, ``weight`` from :meth:`measured_weight`, or a confident prior)."""
        total = (self.buf.prior_conf[k].numpy() > 0.5) if self.prior.metric else np.zeros(weight.shape, bool)
        return total | (weight >= 1.0)

    def moved(self, keyframes, sequence, lost, kept) -> list:
        """For estimated depth: the new grid depth of every mapped keyframe of ``keyframes``,
        its pose and its fresh mapping depth targets (:meth:`compute`; ``sequence``: the
        keyframes' frames, ``lost``, ``kept`` as there), for the map to follow
        (:class:`~mcgs_warp.mapping.follow.DepthMoved`, eq. 13 per pixel: its Gaussians follow
        the change, :meth:`~mcgs_warp.mapping.mapper.Mapper.follow`). Exact sensor depth is
        its own target: nothing follows."""
        if self.exact:
            return []
        mapped = [k for k in keyframes if k in self.buf.targets]
        if not mapped:
            return []
        disp, poses = self.buf.disp.numpy(), self.buf.get_poses()  # read once, not per keyframe
        weight = self.measured_weight(mapped)
        out = []
        for k in mapped:
            new = np.where(disp[k] > 0, 1.0 / np.maximum(disp[k], 1e-12), 0.0)
            out.append(DepthMoved(k, poses[k].copy(), new, self.compute(sequence[self.buf.frame_index[k]], k, lost, kept, disp[k], weight[k])))
        return out

    def solved_at(self, k: int, c: int, uv: np.ndarray) -> np.ndarray:
        """Solved depth [M] (m, 0 where nothing measured it) of keyframe ``k``, camera ``c``,
        at full-resolution pixels ``uv`` [M,2]: the nearest grid sample (:meth:`constrained`)."""
        s, spec = self.buf.stride, self.rig.cameras[c]
        g = np.rint((uv - s // 2) / s).astype(int)
        h, w = spec.height // s, spec.width // s
        inside = (g[:, 0] >= 0) & (g[:, 0] < w) & (g[:, 1] >= 0) & (g[:, 1] < h)
        gx, gy = np.clip(g[:, 0], 0, w - 1), np.clip(g[:, 1], 0, h - 1)
        disp = self.buf.disp[k].numpy()[c]
        ok = self.constrained(k, self.measured_weight([k])[k])[c]
        d = disp[gy, gx]
        return np.where(inside & ok[gy, gx] & (d > 0), 1.0 / np.maximum(d, 1e-12), 0.0)

    def solved_at_frame(self, f: int, c: int, uv: np.ndarray) -> np.ndarray:
        """:meth:`solved_at` for frame ``f`` where it is a keyframe, else 0 [M] (the keypoint
        odometry's points on a monocular rig)."""
        k = {int(i): k for k, i in enumerate(self.buf.frame_index)}.get(f)
        return self.solved_at(k, c, uv) if k is not None else np.zeros(len(uv))
