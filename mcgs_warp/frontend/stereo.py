"""Metric depth from the rig itself: sweep stereo between cameras, behind the
:class:`~mcgs_warp.frontend.depth.DepthPrior` interface.

Per keyframe and camera ``a`` the reference view is swept (:mod:`mcgs_warp.kernels.sweep`)
against every camera ``b`` of the rig whose field of view overlaps ``a``'s at the same
timestamp (``T_b_a = inv(T_b_c[b]) T_b_c[a]``, known from calibration: the depth is
metric), at ``1/scale`` resolution, and the two directions are checked against each other
(left-right). Once poses are solved, :meth:`RigStereo.time_sweep` sweeps a view against the
same camera at other keyframes (time-baseline multi-view stereo), and
:meth:`RigStereo.temporal_depth` puts the rig pairs' depth behind it: the tracker's mapping
targets take that where MCBA's depth constrains no pixel (a side camera's near road
at speed, a wall only one camera sees; :meth:`~mcgs_warp.system.depth_targets.DepthTargets.compute`).
It is no MCBA prior: there it moved the RGB-only scale by 1.7 % (a temporal depth carries the
trajectory's current scale, so it only holds that scale in place).

Sampling: uniform in inverse depth between ``1/far`` and ``1/near``, ``plane_px`` pixels
of epipolar motion per step for the pair's baseline (``planes`` caps the count); with the
parabola fit this gives about 3 % median depth error at 1/2 resolution on the synthetic rig.

The result per view: depth [H,W] (m, 0 = none) and confidence [H,W] in [0,1] at full
resolution (nearest upsampling of the sweep), plus, per overlapping camera pair, the
sweep itself, which :class:`~mcgs_warp.frontend.flow.StereoMatches` turns into
cross-view correspondences.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..rig import CameraSpec, Rig


KEEP = 64  # frames whose stereo depth stays cached in float32 at sweep resolution; older ones are archived in float16


def scaled_spec(spec: CameraSpec, factor: int) -> CameraSpec:
    """The camera seen on an image downsampled by ``factor`` with area averaging (pixel
    centre ``u'`` covers full-resolution ``factor u' + (factor - 1) / 2``)."""
    from ..buffer import reduced_camera

    return reduced_camera(spec, factor, offset=(factor - 1) / 2.0)


def grey(image: np.ndarray, factor: int) -> np.ndarray:
    """RGB [H,W,3] in [0,1] -> grey [H/f,W/f] float32, area-averaged."""
    import cv2

    g = cv2.cvtColor(np.ascontiguousarray(image, dtype=np.float32), cv2.COLOR_RGB2GRAY)
    if factor > 1:  # whole factor x factor blocks only, as scaled_spec assumes
        g = g[: g.shape[0] // factor * factor, : g.shape[1] // factor * factor]
        g = cv2.resize(g, (g.shape[1] // factor, g.shape[0] // factor), interpolation=cv2.INTER_AREA)
    return g


@dataclass
class StereoConfig:
    scale: int = 2  # sweep at 1/scale resolution
    near: float = 0.3  # m: nearest hypothesis, or nearer than that where the pair's disparity there would exceed max_disparity
    max_disparity: float = 0.5  # fraction of the image width: the nearest hypothesis moves out to the depth with this disparity (a wide baseline spends no planes on depths no camera pair can see; KITTI: 0.62 m)
    far: float = 100.0  # m
    planes: int = 192  # at most this many inverse-depth hypotheses
    plane_px: float = 0.5  # epipolar motion between neighbouring hypotheses, px (sweep resolution)
    radius: int = 3  # ZNCC window (2r+1)^2
    min_std: float = 0.02  # flat reference windows (grey std below this) get no depth
    max_cost: float = 0.5  # 1 - ZNCC of the winner must be below this (ZNCC > 0.5)
    max_ratio: float = 0.9  # uniqueness: best / second-best cost
    lr_px: float = 1.0  # left-right consistency, px at sweep resolution
    temporal_near: float = 1.0  # m: nearest hypothesis of temporal sweeps (closer things are the rig pairs' job)
    temporal_baseline: float = 0.5  # m: a keyframe gets temporal sources once one is this far from it
    temporal_sources: int = 2  # mapping targets: a keyframe pixel whose depth MCBA does not constrain takes the sweep of its view against the same camera at this many keyframes at least temporal_baseline away, the nearest earlier ones of the window (time-baseline MVS; 0: off)
    min_overlap: float = 0.05  # camera pairs sharing less of their views are not swept


class RigStereo:
    """Sweeps of overlapping camera pairs of one rig, computed per keyframe and cached."""

    def __init__(self, rig: Rig, overlap: np.ndarray, config: StereoConfig | None = None, device=None):
        import warp as wp

        from ..kernels.sweep import camera_rays

        self.rig = rig
        self.cfg = cfg = config or StereoConfig()
        self.device = wp.get_device(device)
        self.specs = [scaled_spec(s, cfg.scale) for s in rig.cameras]
        self.cams = [s.warp_camera() for s in self.specs]
        self.rays = [camera_rays(c, self.device) for c in self.cams]
        C = len(rig)
        self.pairs = [(a, b) for a in range(C) for b in range(C) if a != b and overlap[a, b] >= cfg.min_overlap and overlap[b, a] >= cfg.min_overlap]
        self._cache: dict = {}
        self._depths: OrderedDict = OrderedDict()  # key -> [(depth, confidence)] per camera of recent frames
        self._archive: dict = {}  # key -> the same in float16, for frames that left the recent ones

    def near(self, baseline: float, focal: float, width: int) -> float:
        """Nearest hypothesis (m) of a pair: ``cfg.near``, or the depth whose disparity is
        ``max_disparity`` of the image width if that is farther (sweep-resolution px)."""
        return max(self.cfg.near, focal * baseline / max(self.cfg.max_disparity * width, 1e-6))

    def hypotheses(self, baseline: float, focal: float, width: int) -> np.ndarray:
        """Inverse-depth hypotheses of a pair (``baseline`` m, ``focal`` and ``width`` in
        sweep-resolution px): ``plane_px`` of epipolar motion apart, at most ``planes``."""
        from ..kernels.sweep import inverse_depth_hypotheses

        cfg = self.cfg
        near = self.near(baseline, focal, width)
        step = cfg.plane_px / max(focal * baseline, 1e-6)  # inverse depth per plane_px of epipolar motion
        n = int(np.clip(np.ceil((1.0 / near - 1.0 / cfg.far) / step), 8, cfg.planes))
        return inverse_depth_hypotheses(near, cfg.far, n)

    def pair_sweeps(self, key, images) -> dict:
        """``{(a, b): SweepResult}`` of every overlapping pair (a swept against b), left-right
        checked; ``key`` identifies the frame for the cache."""
        from ..kernels.sweep import left_right_check, sweep

        if key in self._cache:
            return self._cache[key]
        cfg, rig = self.cfg, self.rig
        greys = [grey(im, cfg.scale) for im in images]
        out = {}
        for a, b in self.pairs:
            T_b_a = np.linalg.inv(rig.cameras[b].T_b_c) @ rig.cameras[a].T_b_c
            rho = self.hypotheses(float(np.linalg.norm(T_b_a[:3, 3])), self.specs[a].intrinsics[0], self.specs[a].width)
            out[(a, b)] = sweep(greys[a], self.rays[a], [greys[b]], [self.cams[b]], T_b_a[None], rho, cfg.radius, cfg.min_std, 1, cfg.max_cost, cfg.max_ratio, device=self.device)
        for a, b in self.pairs:
            T_b_a = np.linalg.inv(rig.cameras[b].T_b_c) @ rig.cameras[a].T_b_c
            left_right_check(out[(a, b)], self.rays[a], self.cams[a], out[(b, a)], self.rays[b], self.cams[b], T_b_a, cfg.lr_px, device=self.device)
        self._cache = {key: out}  # the current keyframe only: sweeps are cheap to redo, memory is not
        return out

    def depth(self, key, images) -> tuple[list, list]:
        """Per camera: depth [H,W] (m, 0 = none) and confidence [H,W] at full resolution,
        the most confident pair per pixel (:meth:`rig_views` upsampled)."""
        f = self.cfg.scale
        views = self.rig_views(key, images)
        return [upsample_nearest(d, spec, f) for (d, _c), spec in zip(views, self.rig.cameras)], [upsample_nearest(c, spec, f) for (_d, c), spec in zip(views, self.rig.cameras)]

    def rig_views(self, key, images) -> list:
        """Per camera at sweep resolution: depth (m, 0 = none) and confidence [h,w] from the
        most confident pair per pixel. The last ``KEEP`` frames' results are kept in
        float32 (the mapper asks again for every keyframe of the window after each solve);
        older ones in float16 (2 bytes a value, 5e-4 relative), because global BA asks
        again for every keyframe's: sweeping them all again cost a 143-keyframe street
        drive 52 s of its global BA."""
        if key in self._depths:
            self._depths.move_to_end(key)
            return self._depths[key]
        if key in self._archive:
            return [(d.astype(np.float32), c.astype(np.float32)) for d, c in self._archive[key]]
        views = self._depths[key] = [self._rig_view(key, images, c) for c in range(len(self.rig))]
        while len(self._depths) > KEEP:
            old, kept = self._depths.popitem(last=False)
            self._archive[old] = [(d.astype(np.float16), c.astype(np.float16)) for d, c in kept]
        return views

    def _rig_view(self, key, images, c: int):
        """Sweep-resolution depth and confidence [h,w] of camera ``c`` from its most
        confident rig pair per pixel (:meth:`rig_views`)."""
        sweeps = self.pair_sweeps(key, images)
        h, w = self.specs[c].height, self.specs[c].width
        best_d, best_c = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
        for (a, _b), res in sweeps.items():
            if a != c:
                continue
            d, conf = res.depth(), res.confidence.numpy()
            take = conf > best_c
            best_d[take], best_c[take] = d[take], conf[take]
        return best_d, best_c

    def time_sweep(self, c: int, image, sources) -> tuple[np.ndarray, np.ndarray]:
        """Depth (m, 0 = none) and confidence [h,w] at sweep resolution of camera ``c``'s view
        ``image`` swept against ``sources``, a non-empty list of ``(image, T_src_ref)``: the
        same camera at other times (``T_src_ref`` 4x4 from solved poses, so the depth has
        the trajectory's scale). Hypotheses from ``temporal_near`` to ``far``, ``plane_px``
        apart for the longest baseline."""
        from ..kernels.sweep import inverse_depth_hypotheses, sweep

        cfg = self.cfg
        Ts = np.stack([T for _im, T in sources])
        base = max(float(np.linalg.norm(T[:3, 3])) for T in Ts)
        step = cfg.plane_px / max(self.specs[c].intrinsics[0] * base, 1e-6)
        n = int(np.clip(np.ceil((1.0 / cfg.temporal_near - 1.0 / cfg.far) / step), 8, cfg.planes))
        rho = inverse_depth_hypotheses(cfg.temporal_near, cfg.far, n)
        res = sweep(grey(image, cfg.scale), self.rays[c], [grey(im, cfg.scale) for im, _T in sources], [self.cams[c]] * len(sources), Ts, rho, cfg.radius, cfg.min_std, 1, cfg.max_cost, cfg.max_ratio, device=self.device)
        return res.depth(), res.confidence.numpy()

    def temporal_depth(self, key, images, sources) -> list:
        """Per camera ``c``: depth [h,w] (m, 0 = none) at sweep resolution (upsample with
        :func:`upsample_nearest`): :meth:`time_sweep` against ``sources[c]`` (a list of
        ``(image, T_src_ref)``, the same camera at other keyframes) where it is confident,
        else the rig pairs' (:meth:`rig_views`). The time sweep comes first: its baselines
        are the rig's travel, mostly longer than a pair's, and its sources are the same
        camera (street seed 12, RGB only: depth L1 0.65 m; taking per pixel the estimate
        with the most parallax, 0.68 m)."""
        depths = []
        for c, (d, _conf) in enumerate(self.rig_views(key, images)):
            if c < len(sources) and sources[c]:
                td, tc = self.time_sweep(c, images[c], sources[c])
                d = np.where((tc > 0) & (td > 0), td, d)
            depths.append(d.astype(np.float32))
        return depths


def upsample_nearest(a: np.ndarray, spec: CameraSpec, factor: int) -> np.ndarray:
    """[h,w] at 1/factor -> [H,W] of ``spec``; rows/columns beyond ``factor * h`` (odd
    sizes) take the last row/column."""
    up = np.repeat(np.repeat(a, factor, 0), factor, 1)
    out = np.pad(up, ((0, max(spec.height - up.shape[0], 0)), (0, max(spec.width - up.shape[1], 0))), mode="edge")
    return out[: spec.height, : spec.width]
