"""The tracking stage (paper Fig. 3, top; ORB-SLAM3's Tracking): every frame's keypoint
odometry and keyframe test; per new keyframe its start (keypoint odometry, keypoint PnP or
constant velocity), depth prior, MCBA (+ JDSA) over the sliding window on the factor graph's
edges with correspondences measured and re-measured from the current geometry, the health of
each solve (and recovery from a failed one). After the last frame the global-BA backend
(:mod:`.backend`) extends its factor graph and solves over every keyframe with its
:meth:`Tracker.measure` and :meth:`Tracker.solve`.

Its inputs are the sequence's frames; its state is the keyframe buffer's poses and depths
(which it alone writes), the factor graph, the odometry and the keypoint tracks. What the map
must do about it leaves as a list of updates (:meth:`Tracker.take_update`: poses that moved,
depths that changed with their fresh mapping targets, :attr:`Tracker.depth_targets`,
:mod:`.depth_targets`): the tracker never touches the map. Each frame's motion goes to its
trajectory filler (:attr:`Tracker.filler`, :mod:`.trajectory_filler`), which places every
frame after the run.
"""

from __future__ import annotations

import json
import logging
import zipfile
from dataclasses import replace

import numpy as np

from ..ba.edges import TEMPORAL, camera_overlap, camera_pairs, sliding_window
from ..ba.graph import FactorGraph
from ..ba.jdsa import mcba_with_jdsa
from ..ba.keypoint_tracks import KeypointTracks
from ..ba.mcba import MCBA, MCBAConfig
from ..buffer import KeyframeBuffer
from ..data.sequence import Sequence
from ..frontend.depth import choose_prior, grid_depth
from ..frontend.flow import DISFlow, GuidedDIS, GuidedOrRaw, NoCorrespondences, SequenceGroundTruthFlow, StereoMatches
from ..frontend.keyframes import KeyframeSelector
from ..frontend.keypoint_odometry import KeypointOdometry
from ..frontend.keypoint_tracker import KeypointTracker
from ..frontend.stereo import RigStereo
from ..mapping.follow import DepthMoved, PosesMoved
from .config import RunConfig
from .depth_targets import DepthTargets
from .trajectory_filler import TrajectoryFiller, constant_velocity

log = logging.getLogger("mcgs_warp.slam")
INITIAL_DEPTH = 3.0  # m: MCBA's start where nothing is known yet (DROID-SLAM starts from a constant too)


class Tracker:
    """The tracking stage: its parts (below), :meth:`track` per frame, :meth:`add_keyframe`
    per keyframe."""

    def __init__(self, sequence: Sequence, config: RunConfig, buffer: KeyframeBuffer):
        self.seq = sequence
        self.cfg = config
        tc = config.tracking
        self.buf = buffer
        rig_overlap = camera_overlap(sequence.rig, stride=tc.stride)
        self.stereo = RigStereo(sequence.rig, rig_overlap, tc.stereo, device=self.buf.device)
        self.prior = choose_prior(sequence, tc.depth, lambda: self.stereo if self.stereo.pairs else None)
        # Correspondences: where they measure depth, full-resolution DIS with small patches; with
        # exact sensor depth they only constrain the poses, and the preset is cheaper (FlowConfig)
        fc = tc.flow
        self.flow = DISFlow(sigma=fc.sigma) if self.exact_depth and fc.exact_depth_preset else DISFlow(sigma=fc.sigma, finest_scale=fc.finest_scale, patch_size=fc.patch_size, smoothness=fc.smoothness)
        self.guided = GuidedDIS(self.flow)
        self.guided_or_raw = GuidedOrRaw(self.guided, self.flow)
        self.selector = KeyframeSelector(DISFlow(), sequence.rig.cameras, threshold=tc.keyframe_flow)  # a mean flow: half resolution is enough
        # Cross-view edges (eq. 8) constrain only depth; exact sensor depth already fixes it,
        # so with it they cost their sweeps and change nothing (demo: 4.3 vs 4.5 mm SE(3) ATE).
        self.overlap = rig_overlap if tc.cross_view and not self.exact_depth else None
        self.oracle = SequenceGroundTruthFlow(sequence) if tc.correspondences == "ground-truth" else NoCorrespondences() if tc.correspondences == "none" else None
        if tc.correspondences == "none" and not (tc.keypoints and tc.keypoint_weight > 0):
            from ..errors import InputError

            raise InputError(None, "tracking.correspondences", "none leaves only the keypoint tracks: it needs tracking.keypoints true and tracking.keypoint_weight above 0")
        self.stereo_matches = StereoMatches(self.stereo)
        self.keypoints = KeypointTracker(sequence.rig, rig_overlap, self.stereo.pairs, tc.keypoint_matching, seed=config.seed) if tc.keypoints else None
        self.odometry = KeypointOdometry(sequence.rig, rig_overlap, self.stereo.pairs, tc.odometry, tc.keypoint_matching, seed=config.seed) if tc.keypoints else None  # every frame's motion
        self.tracks = KeypointTracks(tc.keypoint_weight) if tc.keypoints and tc.keypoint_weight > 0 else None  # keypoint tracks in MCBA
        self.mcba = MCBA(self.buf, MCBAConfig(iterations=tc.mcba_iterations, huber_delta=tc.huber_px, prior_weight=tc.prior_weight if self.prior.metric else 0.0, variance_components=tc.variance_components))
        self.graph = FactorGraph(self.buf, self.overlap, replace(tc.graph, max_per_view=2 * tc.temporal_radius))  # edges and their correspondences
        self._events: list = []  # what the map must follow since the last update (:meth:`take_update`)
        self.filler = TrajectoryFiller(buffer, sequence.timestamps, self.frame_poses)  # every frame's pose, from the keyframes' and each frame's motion
        self._anchor = None  # the newest keyframe's keypoint pose (PnPResult) or None
        self._geometric, self._grid = None, None  # the last solve's depth-alignment factors (window, factors); grid rays and cameras for them
        self.lost: list = []  # keyframes whose tracking was lost (:meth:`_track_state`): not mapped
        self.kept: list = []  # keyframes whose dense solve failed twice where keypoints placed them or constant velocity carries them (not lost ones): MCBA holds that start and drops their temporal correspondences from then on (:meth:`_recover`)
        self._carried, self._lost_span = False, None  # the last keyframe kept the constant-velocity prediction; the open lost span [first frame, last frame, keyframes]
        self.depth_targets = DepthTargets(buffer, sequence.rig, self.prior, self.stereo, self.graph, self.exact_depth, self.metric_scale, tc.window)  # the mapper's, per keyframe
        self.health: list = []  # per keyframe solve (a recovered keyframe has two): frame, confident fraction, residual level, accepted steps, failure (why, or None)
        if not self.metric_scale:
            from ..errors import warn

            warn(None, f"depth source {self.prior.name!r} and no cross-view edges between overlapping rig cameras: the run is monocular; its trajectory and map have no metric scale (judge it by the Sim(3) ATE)")

    @property
    def exact_depth(self) -> bool:
        """Whether the run has exact sensor depth. It is used as is: MCBA's prior, the
        mapping target and the Gaussian seed from the first keyframe on; no JDSA (rescaling
        it to MCBA's depth would free the metric scale) and no cross-view edges (they
        measure only depth)."""
        return self.prior.metric and self.prior.exact

    @property
    def metric_edges(self) -> bool:
        """Whether correspondences measure metric depth: cross-view edges between overlapping
        rig cameras (known baselines; the graph links a pair that overlaps either way).
        Without them only the prior carries the metric scale, and JDSA holds its mean
        (:func:`~mcgs_warp.ba.jdsa.update_scales`)."""
        return bool(camera_pairs(self.overlap, len(self.seq.rig), self.graph.cfg.min_camera_overlap))

    @property
    def failures(self) -> list:
        """Frame index of every keyframe whose solve was a tracking failure (once each)."""
        return sorted({h["frame"] for h in self.health if h["failure"]})

    @property
    def metric_scale(self) -> bool:
        """Whether the run measures metric scale: a metric depth prior (sensor, rig stereo,
        monocular) or correspondences between rig cameras with known baselines."""
        return bool(self.prior.metric or self.metric_edges)

    @property
    def jdsa_active(self) -> bool:
        """JDSA runs for metric but inexact priors (stereo, monocular-style)."""
        return self.cfg.tracking.jdsa and self.prior.metric and not self.exact_depth

    def track(self, index: int, frame, last_keyframe_images) -> bool:
        """Frame ``index``'s keypoint odometry and the keyframe test against the last
        keyframe's images (None: none yet). Returns whether it becomes a keyframe."""
        if self.odometry is not None:
            self.odometry.track(index, frame.images, frame.depths if self.exact_depth else None, depth_at=None if self.exact_depth or self.stereo.pairs else self._frame_depth)
        if last_keyframe_images is None:
            return True
        # the keyframe test's flows also tell whether the rig stood still since the frame before
        is_kf, motion = self.selector.is_keyframe(last_keyframe_images, frame.images)
        self.filler.record(index, motion)
        return is_kf or index == len(self.seq) - 1

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

    @property
    def guided_flow(self):
        """The correspondences that match around the current geometry (:class:`GuidedDIS`, or
        the oracle of ``--correspondences ground-truth`` / ``none``): what confirms loops."""
        return self.oracle or self.guided

    def solve(self, keyframes, fresh=(), guided_new: bool = False, config=None) -> list:
        """MCBA (+ JDSA) over the graph's active edges among ``keyframes`` in ``flow_rounds``
        outer rounds; between rounds the correspondences of edges touching ``fresh``
        keyframes follow the new geometry. Each pose change, and each depth change of a mapped
        keyframe with its fresh mapping depth targets, is queued for the map to follow
        (:meth:`take_update`). ``config``: the solves' MCBAConfig (default MCBA's own). Returns
        each round's ``(MCBAStats, total correspondence weight)``."""
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
                stats = mcba_with_jdsa(self.mcba, edges, targets, weights, keyframes=keyframes, rounds=1, hold_mean=not self.metric_edges, keypoints=kp, factors=geometric, fixed=self.held(keyframes), config=config)[-1]
            else:
                stats = self.mcba.solve(edges, targets, weights, keyframes=keyframes, keypoints=kp, factors=geometric, fixed=self.held(keyframes), config=config)
            out.append((stats, float(np.nansum(weights))))
            after = self.buf.get_poses()
            if kp is not None:
                self.tracks.update(kp, roots, list(keyframes), after, self._T_b_c)
            self._events.append(PosesMoved(before, after))
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
        from functools import reduce

        from ..ba.pose_factors import RelativePoseFactors

        w, odo = self.cfg.tracking.odometry_weight, self.odometry
        if odo is None or w <= 0:
            return []
        own_depth = self.exact_depth or bool(self.stereo.pairs)
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
        """For estimated depth: the new grid depth of every mapped keyframe of ``keyframes``,
        its pose and its fresh mapping depth targets, queued for the map (eq. 13 per pixel:
        its Gaussians follow the change, :meth:`~mcgs_warp.mapping.mapper.Mapper.follow`).
        Exact sensor depth is its own target: nothing follows."""
        if self.exact_depth:
            return
        mapped = [k for k in keyframes if k in self.buf.targets]
        if not mapped:
            return
        disp, poses = self.buf.disp.numpy(), self.buf.get_poses()  # read once, not per keyframe
        weight = self.depth_targets.measured_weight(mapped)
        for k in mapped:
            new = np.where(disp[k] > 0, 1.0 / np.maximum(disp[k], 1e-12), 0.0)
            self._events.append(DepthMoved(k, poses[k].copy(), new, self.mapping_depths(self.seq[self.buf.frame_index[k]], k, disp[k], weight[k])))

    def take_update(self) -> list:
        """The pose and depth changes since the last call, in order (:class:`PosesMoved`,
        :class:`DepthMoved`): what the map must follow. Tracking never touches the map itself."""
        events, self._events = self._events, []
        return events

    def add_keyframe(self, frame) -> int:
        buf, tc = self.buf, self.cfg.tracking
        poses = buf.get_poses()
        if len(buf) == 0:
            T_init = np.eye(4)  # the world frame is the first rig pose
        elif len(buf) == 1:
            T_init = poses[-1]
        else:
            T_init = constant_velocity(poses[-2], poses[-1], buf.timestamps[-2], buf.timestamps[-1], frame.timestamp)
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
            why = self._health(k, self.solve(window, fresh=set(window[-tc.temporal_radius - 1 :])))
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
        from ..errors import warn

        if self._lost_span is None:
            return
        a, b, n = self._lost_span
        end = f"tracking resumed at frame {resumed_at}" if resumed_at is not None else "it never resumed"
        warn(None, f"frames {a}-{b} ({n} keyframe{'s' if n > 1 else ''}): tracking lost, nothing relocalized them; their poses are the constant-velocity prediction and they are not mapped; {end}")
        self._lost_span = None

    def state_arrays(self, store) -> dict:
        """The tracking stage's state for a checkpoint (``np.savez``): its parts' arrays (the
        factor graph's, whose correspondences go to segment files in the folder ``store``;
        the keypoint tracks', the keypoint odometry's, MCBA's measured noise, the trajectory
        filler's) and its own books as JSON in ``tracker.books`` (every solve's health, the
        lost and kept keyframes, whether the last one kept the constant-velocity prediction,
        the open lost span). Keypoints are not stored: :meth:`load_state_arrays` detects them
        again. The mapping depth targets (:attr:`depth_targets`) travel per keyframe beside
        the checkpoint (:mod:`.checkpoint`)."""
        books = {"health": self.health, "lost": self.lost, "kept": self.kept, "carried": self._carried, "lost_span": self._lost_span}
        return {**self.graph.state_arrays(store), **(self.tracks.state_arrays() if self.tracks is not None else {}),
                **(self.odometry.state_arrays() if self.odometry is not None else {}), **self.mcba.state_arrays(),
                **self.filler.state_arrays(), "tracker.books": np.array(json.dumps(books))}

    def load_state_arrays(self, a: dict, store, source) -> None:
        """Restore :meth:`state_arrays` (``store``: its correspondence folder) into a tracker
        whose keyframe buffer holds the saved keyframes; the keypoints of every keyframe and
        of the odometry's recent frames are detected again (deterministic from the images).
        A missing array raises KeyError; tracks or correspondences that do not fit raise
        :class:`~mcgs_warp.errors.InputError` naming ``source`` (the checkpoint) or ``store``."""
        from ..errors import InputError

        def detect(i):
            return self.keypoints.detect(self.seq[i].images, self.seq[i].depths if self.exact_depth else None)

        if self.keypoints is not None:
            for k, i in enumerate(self.buf.frame_index):
                views = detect(int(i))
                self.keypoints.keep(k, views)
                if self.tracks is not None:
                    self.tracks.add_views(k, views)
        try:
            if self.tracks is not None:
                self.tracks.load_state_arrays(a)
        except ValueError as e:
            raise InputError(source, "tracks.parent", f"{e}; start without --resume") from None
        try:
            if self.odometry is not None:
                self.odometry.load_state_arrays(a, detect)
        except ValueError as e:
            raise InputError(source, "odometry.tracks.parent", f"{e}; start without --resume") from None
        self.mcba.load_state_arrays(a)
        try:
            self.graph.load_state_arrays(a, store)
        except (OSError, ValueError, KeyError, IndexError, EOFError, zipfile.BadZipFile) as e:
            raise InputError(store, None, f"unreadable checkpoint correspondences ({e}); start without --resume") from None
        self.filler.load_state_arrays(a)
        books = json.loads(str(a["tracker.books"]))
        self.health, self.lost, self.kept = books["health"], [int(k) for k in books["lost"]], [int(k) for k in books["kept"]]
        self._carried, self._lost_span = bool(books["carried"]), books["lost_span"]

    @property
    def _solved_points(self):
        """World points of keypoint tracks as MCBA solved them (None without tracks)."""
        return self.tracks.world_points if self.tracks is not None else None

    def _keypoint_depth(self, k: int, c: int, uv: np.ndarray) -> np.ndarray:
        """Solved depth [M] (m, 0 where nothing measured it) of keyframe ``k``, camera ``c``,
        at full-resolution pixels ``uv`` [M,2]: the nearest grid sample (:meth:`DepthTargets.constrained`)."""
        s, spec = self.buf.stride, self.seq.rig.cameras[c]
        g = np.rint((uv - s // 2) / s).astype(int)
        h, w = spec.height // s, spec.width // s
        inside = (g[:, 0] >= 0) & (g[:, 0] < w) & (g[:, 1] >= 0) & (g[:, 1] < h)
        gx, gy = np.clip(g[:, 0], 0, w - 1), np.clip(g[:, 1], 0, h - 1)
        disp = self.buf.disp[k].numpy()[c]
        ok = self.depth_targets.constrained(k, self.depth_targets.measured_weight([k])[k])[c]
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
        from ..errors import warn

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
        second = self._health(k, self.solve(window))
        placed = self._anchor is not None or by_odometry
        if second is None and placed:
            warn(None, f"frame {frame} (keyframe {k}): tracking failure ({why}); recovered from {how}")
            return True
        if second is None:
            warn(None, f"frame {frame} (keyframe {k}): tracking failure ({why}); re-matched around {how}, which no keypoint confirms")
            return False
        buf.set_poses(start[None], start=k)
        # held there by MCBA from now on, its correspondences to other times dropped: also the
        # one failed keyframe constant velocity carries, which the later solves otherwise moved
        # with nothing that measures it (surround rig at 2 Hz, seed 13: steps 1.4x, 0.12x); not
        # a lost one (:meth:`_track_state`), whose dropped matches would leave the keyframes
        # after a lost span nothing to other times
        if placed or not self._carried:
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
        """Keyframe ``k``'s full-resolution depth targets for mapping [H,W] per camera (m, 0 =
        none; :meth:`DepthTargets.compute`), their sweep sources among the keyframes whose
        poses tracking measured (neither :attr:`lost` nor :attr:`kept`)."""
        return self.depth_targets.compute(frame, k, self.lost, self.kept, disp, weight)

    def given_pose(self, index: int):
        """A pose given for frame ``index`` (:class:`~mcgs_warp.system.posed_mapping.PosedTracker`), else None."""
        return None

    def held(self, keyframes):
        """Keyframes whose poses MCBA holds: the first of the window (the gauge) and those kept
        at their start after a failed dense solve (:attr:`kept`); None: the gauge alone."""
        kept = [int(k) for k in keyframes if k in self.kept]
        return {int(keyframes[0]), *kept} if kept else None

    def frame_poses(self, fa: int, fb: int):
        """Poses [frame -> 4x4] that place the frames between keyframes at frames ``fa`` and
        ``fb`` (:class:`~mcgs_warp.system.trajectory_filler.TrajectoryFiller`): the keypoint
        odometry's where it placed every frame of the span, else None."""
        odo = self.odometry
        return odo.poses if odo is not None and odo.span_tracked(fa, fb) else None

    def _frame_depth(self, f: int, c: int, uv: np.ndarray) -> np.ndarray:
        """Solved depth [M] (m, 0 unknown) at pixels ``uv`` of frame ``f``'s camera ``c``
        where that frame is a keyframe (the keypoint odometry's points on a monocular rig)."""
        k = self._keyframe_of.get(f)
        return self._keypoint_depth(k, c, uv) if k is not None else np.zeros(len(uv))

    @property
    def _keyframe_of(self) -> dict:
        return {int(f): k for k, f in enumerate(self.buf.frame_index)}
