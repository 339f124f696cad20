"""The offline stage after the last frame (paper Fig. 3, bottom): global MCBA over all
keyframes with long and confirmed loop edges, a photo-consistency pass over the estimated depth
targets, then joint refinement of map, poses and exposures.

A mixin of :class:`~mcgs_warp.system.slam.SLAM`.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..mapping.refine import joint_refinement

GLOBAL_BA_MIN_OVERLAP = 0.1  # long edges need less shared view: guided flow matches what there is


class OfflineStage:
    def photo_consistent_targets(self, keyframes, radius: int, min_views: int = 0) -> None:
        """Sharpen estimated mapping targets with the solved poses: one PatchMatch-style pass
        (:func:`~mcgs_warp.kernels.propagation.propagate_depth`) per view against the same camera
        up to ``radius`` keyframes either side and the rig's overlapping cameras at the same
        time. MCBA's depth lives on a grid of 8 px cells and is upsampled, so depth edges
        spread over a cell and plain surfaces carry the grid's error; each pixel now takes
        the nearby depth (or a 2-5 % change of its own) that its 9x9 window matches best
        (at depth edges with colour-adaptive window weights, against foreground fattening).
        Then, with ``min_views`` > 0, a target pixel is kept only where at least that many of
        those views' new targets put the point within 5 % of it
        (:func:`~mcgs_warp.kernels.propagation.consistent_depth`); the rest get no depth target."""
        from ..frontend.stereo import grey
        from ..kernels.propagation import consistent_depth, propagate_depth

        buf, rig = self.buf, self.seq.rig
        poses, rays = buf.get_poses(), buf.full_rays
        T_w_c = {(k, c): poses[k] @ spec.T_b_c for k in range(len(buf)) for c, spec in enumerate(rig.cameras)}
        cams = [spec.warp_camera() for spec in rig.cameras]
        greys: dict = {}

        def grey_of(k, c):
            if (k, c) not in greys:
                greys[(k, c)] = grey(buf.images[k][c], 1)
            return greys[(k, c)]

        todo = sorted(k for k in keyframes if k in self.buf.targets)

        def views_of(k, c, mapped: bool = False):
            """The views (keyframe, camera) that judge view (k, c), and T_src_ref [S,4,4]."""
            views = [(k2, c) for k2 in range(max(0, k - radius), min(len(buf), k + radius + 1)) if k2 != k]
            views += [(k, b) for a, b in self.stereo.pairs if a == c]
            views = [v for v in views if v[0] in self.buf.targets] if mapped else views
            return views, np.stack([np.linalg.inv(T_w_c[v]) @ T_w_c[(k, c)] for v in views]) if views else np.zeros((0, 4, 4))

        for n, k in enumerate(todo):
            for key in [key for key in greys if key[0] < k - radius]:
                del greys[key]  # keyframes in order: hold only the views a later one still uses
            targets = []
            for c in range(len(rig)):
                views, T_src_ref = views_of(k, c)
                depth = np.asarray(self.buf.targets[k][c], np.float32)
                targets.append(propagate_depth(grey_of(k, c), rays[c], depth, [grey_of(*v) for v in views], [cams[v[1]] for v in views], T_src_ref, ref_colour=buf.images[k][c], device=buf.device))
            self.buf.targets[k] = targets
            self.progress("photo depth", n + 1, len(todo))
        if min_views <= 0:
            return
        kept = {}  # judged against the other views' unfiltered targets, then replaced together
        for k in todo:
            kept[k] = []
            for c in range(len(rig)):
                views, T_src_ref = views_of(k, c, mapped=True)
                kept[k].append(consistent_depth(rays[c], self.buf.targets[k][c], [rays[v[1]] for v in views], [self.buf.targets[v[0]][v[1]] for v in views], [cams[v[1]] for v in views], T_src_ref, min_views=min_views, device=buf.device))
        self.buf.targets.update(kept)

    def refine(self) -> None:
        rc = self.cfg.refinement
        t0 = time.perf_counter()
        self.poses_before_global_ba = self.buf.get_poses()  # keyframe T_w_b (benchmarks/scaling.py: drift)
        if rc.global_ba_iterations and len(self.buf) > 1:
            self.progress("global BA", 0, 1, force=True)
            everything = list(range(len(self.buf)))
            online = self.graph.cfg
            # long edges: overlapping views up to global_ba_radius keyframes apart, then revisits
            self.graph.cfg = replace(online, max_per_view=2 * rc.global_ba_radius, min_overlap=GLOBAL_BA_MIN_OVERLAP)
            try:
                self.graph.update_window(everything, cross_view=self.overlap is not None, max_gap=rc.global_ba_radius)
            finally:
                self.graph.cfg = online
            self.measure(guided_new=True)
            self.loops = self.graph.close_loops(self.oracle or self.guided)
            saved = self.mcba.cfg.iterations, self.mcba.cfg.prior_weight
            self.mcba.cfg.iterations = rc.global_ba_iterations
            if not self.exact_depth:
                # the long edges measure what the online window could not; an inexact prior,
                # JDSA-scaled to the online estimate, would only hold that estimate in place
                self.mcba.cfg.prior_weight = 0.0
            self._solve(everything, guided_new=True)
            self.mcba.cfg.iterations, self.mcba.cfg.prior_weight = saved
            self.seconds["global_ba"] = time.perf_counter() - t0
            self.progress("global BA", 1, 1, force=True)
            if rc.photo_depth_radius > 0 and not self.exact_depth:
                t1 = time.perf_counter()
                self.photo_consistent_targets(everything, rc.photo_depth_radius, rc.photo_depth_min_views)
                self.seconds["photo_depth"] = time.perf_counter() - t1
        if rc.iterations:
            def report(it, r):
                self.progress("refining", it + 1, rc.iterations, f"psnr {r.psnr:.1f} dB")

            joint_refinement(self.mapper, rc.iterations, poses=rc.poses, exposure=rc.exposure, progress=report)
            self.progress.done()
        self.seconds["refinement"] += time.perf_counter() - t0
