"""The per-keyframe step of the online loop (paper Fig. 3, top): initial pose by constant
velocity, depth from the prior, MCBA (+ JDSA) over the sliding window on the factor graph's
edges with correspondences measured and re-measured from the current geometry, the health of
each solve (and recovery from a failed one), and the mapping depth targets that follow it.

A mixin of :class:`~mcgs_warp.system.slam.SLAM`: it uses the state the pipeline wires up there.
"""

from __future__ import annotations

import logging

import numpy as np

from ..ba.edges import TEMPORAL, sliding_window
from ..ba.jdsa import mcba_with_jdsa, scale_field
from ..frontend.depth import grid_depth, upsample_inverse_depth_guided

log = logging.getLogger("mcgs_warp.slam")
INITIAL_DEPTH = 3.0  # m: MCBA's start where nothing is known yet (DROID-SLAM starts from a constant too)


class KeyframeStep:
    def measure(self, refresh=(), guided_new: bool = False) -> None:
        """Correspondences for the graph's active edges that have none: cross-view edges from
        the rig's sweep stereo, the others from DIS; edges touching a keyframe in ``refresh``
        are re-estimated from the current reprojection (:class:`GuidedDIS`) unless the current
        geometry already predicts their matches (:meth:`GuidedDIS.settled`); ``guided_new``
        computes new non-cross-view edges that way from the start (global BA's long edges:
        their keyframes are already solved, their motion too large for raw DIS), and so does
        exact sensor depth (its prediction is good from the first solve on). With
        ``--correspondences ground-truth`` every edge is exact (oracle); with ``none`` no
        edge has any (:class:`NoCorrespondences`)."""
        g = self.graph
        if self.oracle is None and refresh:
            g.refresh(self.guided, refresh)
        missing = g.missing()
        if not len(missing):
            return
        if self.oracle is not None:
            g.compute(self.oracle, missing)
            return
        cross = np.array([i == j and (ci, cj) in self.stereo.pairs for i, ci, j, cj, _ in missing.tolist()], bool)
        if cross.any():
            g.compute(self.stereo_matches, missing[cross])
        if (~cross).any():
            # with exact depth the constant-velocity start already predicts the flow well: match
            # around it from the start (the re-matching round then finds these edges settled),
            # by plain DIS where the start is too poor to guide (with a keypoint-anchored start
            # and a metric prior too: KITTI SE(3) ATE 0.771 vs 0.778 m, fewer confident matches)
            g.compute(self.guided if guided_new else self.guided_or_raw if self.exact_depth else self.flow, missing[~cross])

    def _solve(self, keyframes, fresh=(), guided_new: bool = False) -> list:
        """MCBA (+ JDSA) over the graph's active edges among ``keyframes`` in ``flow_rounds``
        outer rounds; between rounds the correspondences of edges touching ``fresh``
        keyframes follow the new geometry. Anchored Gaussians follow every pose and depth
        change, and the mapping depth targets are refreshed. Returns each round's
        ``(MCBAStats, total correspondence weight)``."""
        rounds = max(1, self.cfg.tracking.flow_rounds)
        out = []
        for r in range(rounds):
            self.measure(refresh=fresh if r > 0 else (), guided_new=guided_new)
            edges, targets, weights = self.graph.arrays(keyframes)
            if self.kept:  # a kept keyframe's matches to other times failed: they would pull its neighbours
                drop = np.isin(edges[:, 0], self.kept) | np.isin(edges[:, 2], self.kept)
                drop &= edges[:, 0] != edges[:, 2]
                if drop.any():
                    weights = np.where(drop[:, None, None], np.float32(0.0), weights)
            before = self.buf.get_poses()
            kp, roots = self._keypoint_problem(keyframes, before)
            geometric = self._depth_factors(keyframes, edges) + self._odometry_factors(keyframes)
            if self.jdsa_active:
                stats = mcba_with_jdsa(self.mcba, edges, targets, weights, keyframes=keyframes, rounds=1, hold_mean=not self.metric_edges, keypoints=kp, factors=geometric, fixed=self.held(keyframes))[-1]
            else:
                stats = self.mcba.solve(edges, targets, weights, keyframes=keyframes, keypoints=kp, factors=geometric, fixed=self.held(keyframes))
            out.append((stats, float(np.nansum(weights))))
            after = self.buf.get_poses()
            if kp is not None:
                self.tracks.update(kp, roots, list(keyframes), after, self._T_b_c)
            self.mapper.map.follow_keyframes(before, after)
        self._follow_depths(keyframes)
        return out

    def _depth_factors(self, keyframes, edges) -> list:
        """Sensor-depth alignment over the window's edges between keyframes (exact sensor
        depth only, ``tracking.depth_weight`` > 0); kept for the health check."""
        from ..ba.depth_factors import DepthAlignmentFactors

        w = self.cfg.tracking.depth_weight
        self._geometric = None
        if not self.exact_depth or w <= 0:
            return []
        keyframes = list(keyframes)
        slot = {k: s for s, k in enumerate(keyframes)}
        pairs = np.array([(slot[i], ci, slot[j], cj) for i, ci, j, cj in np.asarray(edges)[:, :4].tolist() if i != j], int).reshape(-1, 4)
        if not len(pairs):
            return []
        buf = self.buf
        if self._grid is None:
            self._grid = (buf.rays.numpy().astype(np.float64), [c.warp_camera() for c in buf.reduced])
        depth = buf.depth_prior.numpy()[keyframes]
        f = DepthAlignmentFactors(pairs, depth, *self._grid, self._T_b_c, w, self.mcba.cfg.huber_delta)
        self._geometric = (keyframes, f)
        return [f]

    def _odometry_factors(self, keyframes) -> list:
        """The keypoint odometry's motion between consecutive keyframes of ``keyframes``
        where it placed every frame between them, weighted by its information times
        ``tracking.odometry_weight`` (:class:`~mcgs_warp.ba.pose_factors.RelativePoseFactors`);
        only where its keypoints have depth of their own (sensor depth or rig stereo). On a rig
        without either (front + back cameras, a mono prior) it placed its points on this
        system's solved depth: as a factor it pulled the window's scale 4 % off (0.6 cm -> 2.5 cm
        on 1.7 m, tests/system/test_rgb_only.py)."""
        from ..ba.pose_factors import RelativePoseFactors

        w, odo = self.cfg.tracking.odometry_weight, self.odometry
        if odo is None or w <= 0 or not (self.exact_depth or self.stereo.pairs):
            # without sensor depth or rig stereo its points come from this window's own depth: no
            # independent measurement, and its covariance (which MCBA's class weights trust) overstates it
            return []
        keyframes = list(keyframes)
        pairs, motions, info = [], [], []
        for s in range(1, len(keyframes)):
            fa, fb = int(self.buf.frame_index[keyframes[s - 1]]), int(self.buf.frame_index[keyframes[s]])
            if not odo.span_tracked(fa, fb):
                continue
            cov = odo.relative_covariance(fa, fb)
            try:
                lam = np.linalg.inv(cov)
            except np.linalg.LinAlgError:
                continue
            if not np.all(np.isfinite(lam)):
                continue
            pairs.append((s - 1, s))
            motions.append(odo.relative(fa, fb))
            info.append(w * 0.5 * (lam + lam.T))
        return [RelativePoseFactors(pairs, motions, info)] if pairs else []

    @property
    def _T_b_c(self) -> np.ndarray:
        return np.stack([c.T_b_c for c in self.seq.rig.cameras])

    def _keypoint_problem(self, keyframes, poses):
        """The keypoint tracks of ``keyframes`` as an MCBA problem (None without tracks)."""
        if self.tracks is None:
            return None, []
        return self.tracks.problem(list(keyframes), lambda k: self.keypoints.views[k], poses, self._T_b_c, self._keypoint_depth)

    def _confident_fractions(self, k: int) -> tuple[float, list]:
        """Fraction of keyframe ``k``'s grid pixels with a confident (weight > 0.5)
        correspondence to another keyframe, or whose sensor depth the other keyframes' depth
        agrees with (:meth:`_depth_factors`): over all cameras, and per camera [C]."""
        C, s = len(self.seq.rig), self.buf.stride
        area = np.array([(c.height // s) * (c.width // s) for c in self.seq.rig.cameras], np.float64)
        rows = [n for n, e in enumerate(self.graph.edges) if e[0] == k and e[2] != k]
        linked = np.zeros((C, self.buf.h, self.buf.w), bool)
        if rows:
            edges = self.graph.edges[rows]
            _, w = self.graph.correspondences(edges)
            for e, wt in zip(edges, w):
                linked[int(e[1])] |= wt > 0.5
        geo = self._geometric
        if geo is not None and k in geo[0]:  # sensor depth that agrees (and places the keyframe) counts as a confident match
            keyframes, f = geo
            ok = f.agreement(self.buf.get_poses()[keyframes], keyframes.index(k))
            for dy in range(f.step):
                for dx in range(f.step):
                    linked[f.ci[ok], np.minimum(f.ys[ok] + dy, self.buf.h - 1), np.minimum(f.xs[ok] + dx, self.buf.w - 1)] = True
        per = linked.sum(axis=(1, 2)) / np.maximum(area, 1)
        return float(linked.sum()) / max(area.sum(), 1), [round(float(f), 4) for f in per]

    def _health(self, k: int, rounds: list) -> str | None:
        """Why the solve that added keyframe ``k`` is a tracking failure, or None: no MCBA
        step accepted in any round, too few confident correspondences, or a final robust cost
        per unit of correspondence weight far above the run's usual level."""
        th = self.cfg.tracking
        frac, per_camera = self._confident_fractions(k)
        stats, weight = rounds[-1]
        level = stats.dense_cost[-1] / max(weight, 1e-9) if stats.dense_cost else float("nan")  # the other classes' weights change over a run
        healthy = [h["residual"] for h in self.health if not h["failure"] and np.isfinite(h["residual"])]
        usual = float(np.median(healthy)) if len(healthy) >= 3 else None
        why = None
        if all(st.accepted == 0 for st, _ in rounds) and any(st.cost for st, _ in rounds):
            why = "no MCBA step accepted"
        elif frac < th.min_confident and th.correspondences != "none":
            why = f"only {100 * frac:.1f} % of its pixels have a confident correspondence (tracking.min_confident {100 * th.min_confident:g} %)"
        elif usual is not None and np.isfinite(level) and level > th.max_residual_ratio * usual:
            why = f"residual {level:.3g} is {level / usual:.0f}x the run's median (tracking.max_residual_ratio {th.max_residual_ratio:g})"
        anchor = self._anchor
        self.health.append({"keyframe": k, "frame": int(self.buf.frame_index[k]), "confident": round(frac, 4), "confident_per_camera": per_camera, "residual": float(level), "accepted": int(sum(st.accepted for st, _ in rounds)),
                            "keypoint_inliers": None if anchor is None else anchor.n_inliers, "keypoint_matches": None if anchor is None else anchor.n_matches,
                            "dense_sigma": None if stats.noise is None else round(float(np.sqrt(stats.noise.sigma2)), 5), "dense_kappa": None if stats.noise is None else round(stats.noise.kappa, 2),
                            "dense_disagreement": None if stats.disagreement is None else float(stats.disagreement),
                            "class_weights": [round(x, 4) for x in stats.scales], "failure": why})
        return why

    def _follow_depths(self, keyframes) -> None:
        """Eq. 13 per pixel, and fresh mapping targets, for estimated depth: the Gaussians of a
        mapped keyframe follow MCBA/JDSA's change of its depth along the rays of the camera
        they were seen from (ratio of new to old grid depth at their pixel, 3x3 median), so a
        keyframe whose far depth improves takes its Gaussians along; its depth targets become
        the new estimate. Exact sensor depth is its own target: nothing follows."""
        if self.exact_depth:
            return
        mapped = [k for k in keyframes if k in self.buf.targets]
        if not mapped:
            return
        disp, poses = self.buf.disp.numpy(), self.buf.get_poses()  # read once, not per keyframe
        weight = self._measured_weight(mapped)
        for k in mapped:
            new, old = np.where(disp[k] > 0, 1.0 / np.maximum(disp[k], 1e-12), 0.0), self._mapped_depth[k]
            ratio = depth_ratio(old, new)
            self.mapper.map.follow_depth(k, poses[k], self.seq.rig, self.buf.cameras, ratio)
            # what the Gaussians now stand for: the part of the change the filter or clip held back stays due
            self._mapped_depth[k] = np.where((old > 0) & (new > 0), old * ratio, new)
            self.buf.targets[k] = self.mapping_depths(self.seq[self.buf.frame_index[k]], k, disp[k], weight[k])

    def add_keyframe(self, frame) -> int:
        buf, tc = self.buf, self.cfg.tracking
        poses = buf.get_poses()
        if len(buf) == 0:
            T_init = np.eye(4)  # the world frame is the first rig pose
        elif len(buf) == 1:
            T_init = poses[-1]
        else:
            T_init = poses[-1] @ np.linalg.inv(poses[-2]) @ poses[-1]  # constant velocity
        odo = self.odometry
        if len(buf) and odo is not None and odo.span_tracked(int(buf.frame_index[-1]), frame.index):
            T_init = poses[-1] @ odo.relative(int(buf.frame_index[-1]), frame.index)  # the keypoint odometry's motion since the last keyframe
        given = self.given_pose(frame.index)
        if given is not None:
            T_init = given
        views, self._anchor = None, None
        if self.keypoints is not None:
            views = odo.views[frame.index] if odo is not None and frame.index in odo.views else self.keypoints.detect(frame.images, frame.depths if self.exact_depth else None)
            if len(buf):
                recent = [j for j in range(len(buf)) if j not in self.lost][-self.keypoints.cfg.keyframes :]  # a lost keyframe's pose is only a prediction
                self._anchor = self.keypoints.localize(views, recent, poses, self._keypoint_depth, guess=T_init, solved=self._solved_points)
                if self._anchor is not None:
                    T_init = self._anchor.T_w_b
        depths, confs = self.prior.with_confidence(frame, self.seq.rig)
        prior = grid_depth(depths, self.seq.rig, tc.stride, (buf.h, buf.w))
        conf = grid_depth(confs, self.seq.rig, tc.stride, (buf.h, buf.w))
        if (prior > 0).any():
            fill = float(np.median(prior[prior > 0]))
        elif len(buf):
            d = buf.depth(len(buf) - 1)
            fill = float(np.median(d[d > 0])) if (d > 0).any() else INITIAL_DEPTH
        else:
            fill = INITIAL_DEPTH
        disp = np.where(prior > 0, 1.0 / np.maximum(prior, 1e-6), 1.0 / fill).astype(np.float32)
        k = buf.add(frame.index, frame.timestamp, frame.images, T_init, disp, depth_prior=prior if self.prior.metric else None, prior_conf=conf)
        if views is not None:
            self.keypoints.keep(k, views)
            if self.tracks is not None:
                self.tracks.add_views(k, views)
                if self._anchor is not None:
                    self.tracks.link(k, self._anchor.matches)
        if len(buf) > 1:
            window = sliding_window(len(buf), tc.window)
            self.graph.update_window(window, cross_view=self.overlap is not None)
            self._link_newest(k)
            why = self._health(k, self._solve(window, fresh=set(window[-tc.temporal_radius - 1 :])))
            tracked = why is None or self._recover(k, window, T_init, disp, why)
            self._track_state(k, tracked)
        return k

    def _track_state(self, k: int, tracked: bool) -> None:
        """Lost tracking: constant velocity carries the pose through one failed keyframe at
        most. A second one in a row that nothing relocalizes is lost, and so is every one
        after it until a keyframe tracks again: lost keyframes keep the prediction (the
        trajectory needs a pose) but are not mapped, and the span gets one warning line when
        tracking resumes (or at the end, :meth:`close_lost_span`)."""
        if tracked:
            self._carried = False
            self.close_lost_span(resumed_at=int(self.buf.frame_index[k]))
            return
        if self._carried:
            self.lost.append(k)
            frame = int(self.buf.frame_index[k])
            self._lost_span = [frame if self._lost_span is None else self._lost_span[0], frame, (0 if self._lost_span is None else self._lost_span[2]) + 1]
        self._carried = True

    def close_lost_span(self, resumed_at: int | None = None) -> None:
        """Say that tracking was lost (one warning line with the span), once it has ended."""
        from ..data.sequence import warn

        if self._lost_span is None:
            return
        a, b, n = self._lost_span
        end = f"tracking resumed at frame {resumed_at}" if resumed_at is not None else "it never resumed"
        warn(None, f"frames {a}-{b} ({n} keyframe{'s' if n > 1 else ''}): tracking lost, nothing relocalized them; their poses are the constant-velocity prediction and they are not mapped; {end}")
        self._lost_span = None

    @property
    def _solved_points(self):
        """World points of keypoint tracks as MCBA solved them (None without tracks)."""
        return self.tracks.world_points if self.tracks is not None else None

    def _keypoint_depth(self, k: int, c: int, uv: np.ndarray) -> np.ndarray:
        """Solved depth [M] (m, 0 where nothing measured it) of keyframe ``k``, camera ``c``,
        at full-resolution pixels ``uv`` [M,2]: the nearest grid sample (:meth:`_constrained`)."""
        s, spec = self.buf.stride, self.seq.rig.cameras[c]
        g = np.rint((uv - s // 2) / s).astype(int)
        h, w = spec.height // s, spec.width // s
        inside = (g[:, 0] >= 0) & (g[:, 0] < w) & (g[:, 1] >= 0) & (g[:, 1] < h)
        gx, gy = np.clip(g[:, 0], 0, w - 1), np.clip(g[:, 1], 0, h - 1)
        disp = self.buf.disp[k].numpy()[c]
        ok = self._constrained(k, self._measured_weight([k])[k])[c]
        d = disp[gy, gx]
        return np.where(inside & ok[gy, gx] & (d > 0), 1.0 / np.maximum(d, 1e-12), 0.0)

    def _recover(self, k: int, window, T_init: np.ndarray, disp0: np.ndarray, why: str) -> bool:
        """A tracking failure at keyframe ``k``: one warning line, then re-initialize it,
        relocalized by its keypoints against every keyframe where they give a pose (else
        from ``T_init``, the keypoint or constant-velocity start), with start depth
        ``disp0``; drop its correspondences, match them again from that start (guided by the
        older keyframes' solved depth, plain DIS where the start cannot guide) and solve
        again. If that fails too, ``k`` keeps the start. Returns whether ``k`` is tracked:
        placed by keypoints (relocalized, anchored, or every frame since the last keyframe
        placed by the keypoint odometry) and solved or at least kept there. Re-matching around
        the constant-velocity prediction alone places nothing: guided matching on images
        that match nothing (sensor noise) finds a consistent flow around any prediction."""
        from ..data.sequence import warn

        buf = self.buf
        frame = buf.frame_index[k]
        odo = self.odometry
        by_odometry = k > 0 and odo is not None and odo.span_tracked(int(buf.frame_index[k - 1]), int(frame))
        start, how = T_init, "the keypoint pose" if self._anchor is not None else "the keypoint odometry's pose" if by_odometry else "the constant-velocity prediction"
        if self.keypoints is not None and k in self.keypoints.views:
            others = [j for j in range(len(buf)) if j != k and j not in self.lost]
            reloc = self.keypoints.localize(self.keypoints.views[k], others, buf.get_poses(), self._keypoint_depth, solved=self._solved_points)
            if reloc is not None:
                start, how = reloc.T_w_b, f"relocalized by keypoints ({reloc.n_inliers} inliers)"
                self._anchor = reloc
                if self.tracks is not None:
                    self.tracks.link(k, reloc.matches)
        buf.set_poses(start[None], start=k)
        buf.disp[k].assign(np.asarray(disp0, dtype=np.float32))
        own = np.array([e for e in self.graph.edges if (e[0] == k) != (e[2] == k)], np.int32).reshape(-1, 5)  # k's edges to other keyframes
        self.graph.forget(own)
        self.graph.add(own)
        self.graph.compute(self.guided_or_raw, self.graph.missing())
        second = self._health(k, self._solve(window))
        placed = self._anchor is not None or by_odometry
        if second is None and placed:
            warn(None, f"frame {frame} (keyframe {k}): tracking failure ({why}); recovered from {how}")
            return True
        if second is None:
            warn(None, f"frame {frame} (keyframe {k}): tracking failure ({why}); re-matched around {how}, which no keypoint confirms")
            return False
        buf.set_poses(start[None], start=k)
        if placed:  # held there by MCBA from now on, its correspondences to other times dropped
            self.kept.append(k)
        warn(None, f"frame {frame} (keyframe {k}): tracking failure ({why}; again after re-matching: {second}); keyframe {k} keeps {how}")
        return placed

    def _link_newest(self, k: int) -> None:
        """A new keyframe whose views overlap no one else's by the graph's measure (a fast
        turn, a poor constant-velocity start) would not be tracked at all: link each of its
        cameras to the previous keyframe's, as DROID-SLAM always keeps the nearest edge."""
        linked = {int(ci) for i, ci, j, _cj, _kind in self.graph.edges if i == k and j != k}
        lonely = [c for c in range(len(self.seq.rig)) if c not in linked]
        if lonely:
            self.graph.add([(k, c, k - 1, c, TEMPORAL) for c in lonely] + [(k - 1, c, k, c, TEMPORAL) for c in lonely])
            log.warning("keyframe %d: camera(s) %s overlap no view of the window; linked to keyframe %d", k, lonely, k - 1)

    def mapping_depths(self, frame, k: int, disp=None, weight=None) -> list:
        """Full-resolution depth targets for mapping (which also seed its Gaussians): exact
        sensor depth as is; otherwise the current estimate (MCBA depth where correspondences
        or a prior constrain it, upsampled guided by the image, which fills up to a grid cell
        around constrained samples), sharpened by the JDSA-scaled
        prior where the two agree within 10 %. (Keeping only well-measured pixels as
        targets was tried: far regions then drift further, depth L1 0.34 -> 0.47 m.)"""
        import cv2

        if self.exact_depth:
            return list(frame.depths)
        buf, s = self.buf, self.buf.stride
        disp = buf.disp.numpy()[k] if disp is None else disp
        constrained = self._constrained(k, self._measured_weight([k])[k] if weight is None else weight)
        depths = self.prior(frame, self.seq.rig) if self.prior.metric else [None] * len(self.seq.rig)
        grids = buf.scales[k].numpy()  # [C,m,n]
        out = []
        for c, spec in enumerate(self.seq.rig.cameras):
            h, w = spec.height // s, spec.width // s
            full = upsample_inverse_depth_guided(np.where(constrained[c, :h, :w], disp[c, :h, :w], 0.0), spec, s, frame.images[c], device=buf.device)
            if depths[c] is not None:
                # the JDSA field lives on the buffer's grid (buf.h x buf.w), this camera's part [:h,:w]
                field = scale_field(grids[c], buf.h, buf.w)[:h, :w].astype(np.float32)
                scaled = depths[c] * cv2.resize(field, (spec.width, spec.height), interpolation=cv2.INTER_LINEAR)
                agree = (scaled > 0) & (full > 0) & (np.abs(scaled - full) < 0.1 * full)
                full = np.where(agree, scaled, full)
            out.append(full)
        return out

    def _measured_weight(self, keyframes) -> dict:
        """Per keyframe [C,h,w]: summed correspondence confidence of every edge (active or
        stored) leaving each of its grid pixels (:meth:`FactorGraph.measured_weight`)."""
        return {k: self.graph.measured_weight(k, len(self.seq.rig)) for k in set(keyframes)}

    def _constrained(self, k: int, weight: np.ndarray) -> np.ndarray:
        """[C,h,w] bool: grid pixels of keyframe k whose depth something measured (confident
        correspondences from the view, ``weight`` from :meth:`_measured_weight`, or a confident prior)."""
        total = (self.buf.prior_conf[k].numpy() > 0.5) if self.prior.metric else np.zeros(weight.shape, bool)
        return total | (weight >= 1.0)


def depth_ratio(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Per-pixel ``new / old`` [C,h,w] of two grid depths (1 where either is unknown),
    3x3-median filtered (one noisy pixel moves no Gaussian) and clipped to [0.5, 2]."""
    import cv2

    ok = (old > 0) & (new > 0)
    r = np.where(ok, new / np.where(ok, old, 1.0), 1.0).astype(np.float32)
    return np.clip(np.stack([cv2.medianBlur(x, 3) for x in r]), 0.5, 2.0)
