"""The tracking stage (paper Fig. 3, top; ORB-SLAM3's Tracking): every frame's keypoint
odometry and keyframe test; per new keyframe its start (keypoint odometry, keypoint PnP or
constant velocity), depth prior, MCBA (+ JDSA) over the sliding window on the factor graph's
edges with correspondences measured and re-measured from the current geometry, the health of
each solve (and recovery from a failed one). After the last frame the global-BA backend
(:mod:`.backend`) extends its factor graph and solves over every keyframe with its
:meth:`Tracker.measure` and :meth:`Tracker.solve`.

Its inputs are the sequence's frames; its state is the keyframe buffer's poses and depths
(which it alone writes), the factor graph, the odometry and the keypoint tracks. What the map
must do about a new keyframe leaves as one
:class:`~mcgs_warp.mapping.follow.KeyframeUpdate` (:meth:`Tracker.add_keyframe`): poses that
moved, depths that changed with their fresh mapping targets (:attr:`Tracker.depth_targets`,
:mod:`.depth_targets`), then the keyframes to register with their targets, after the
bootstrap rule and without lost ones; the tracker never touches the map. Its parts in their
own modules: the solves' geometric factors (:mod:`.window_factors`), the health check
(:mod:`.health`), the lost and kept keyframes (:mod:`.lost_tracking`). Each frame's motion
goes to its trajectory filler (:attr:`Tracker.filler`, :mod:`.trajectory_filler`), which
places every frame after the run.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from ..ba.edges import camera_overlap, camera_pairs, sliding_window
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
from ..mapping.follow import KeyframeUpdate, PosesMoved, Registration
from . import tracker_state
from .config import RunConfig
from .depth_targets import DepthTargets
from .health import SolveHealth
from .lost_tracking import LostTracking
from .trajectory_filler import TrajectoryFiller, constant_velocity
from .window_factors import WindowFactors

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
        self.guided = GuidedDIS(self.flow, settled_px=fc.settled_px, settled_outliers=fc.settled_outliers, photo_sigma=fc.photo_sigma)
        self.guided_or_raw = GuidedOrRaw(self.guided, self.flow, min_confident=fc.min_confident)
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
        self.odometry = KeypointOdometry(sequence.rig, config=tc.odometry, tracker=self.keypoints) if tc.keypoints else None  # every frame's motion, the same keypoint tracker
        self.keyframe_views: dict = {}  # keyframe -> its keypoints per camera (the odometry keeps its recent frames')
        self.tracks = KeypointTracks(tc.keypoint_weight) if tc.keypoints and tc.keypoint_weight > 0 else None  # keypoint tracks in MCBA
        self.mcba = MCBA(self.buf, MCBAConfig(iterations=tc.mcba_iterations, huber_delta=tc.huber_px, lm_lambda=tc.lm_lambda, prior_weight=tc.prior_weight if self.prior.metric else 0.0, variance_components=tc.variance_components))
        self.graph = FactorGraph(self.buf, self.overlap, replace(tc.graph, max_per_view=2 * tc.temporal_radius))  # edges and their correspondences
        self._events: list = []  # what the map must follow since the last update (:meth:`take_update`)
        self.filler = TrajectoryFiller(buffer, sequence.timestamps, self.frame_poses)  # every frame's pose, from the keyframes' and each frame's motion
        self._anchor = None  # the newest keyframe's keypoint pose (PnPResult) or None
        self.factors = WindowFactors(buffer, sequence.rig, tc, self.odometry, self.exact_depth, self.exact_depth or bool(self.stereo.pairs), self.mcba)  # sensor depth, odometry
        self.lost_tracking = LostTracking()  # the lost and kept keyframes
        self.depth_targets = DepthTargets(buffer, sequence.rig, self.prior, self.stereo, self.graph, self.exact_depth, self.metric_scale, tc.window)  # the mapper's, per keyframe
        self.checks = SolveHealth(self.graph, buffer, sequence.rig, tc)  # every solve's health
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
        return self.checks.failures

    @property
    def health(self) -> list:
        """Per keyframe solve (a recovered keyframe has two) its health record (:mod:`.health`)."""
        return self.checks.records

    @property
    def lost(self) -> list:
        """Keyframes whose tracking was lost: not mapped (:mod:`.lost_tracking`)."""
        return self.lost_tracking.lost

    @property
    def kept(self) -> list:
        """Keyframes MCBA holds at their start after a failed dense solve (:meth:`_recover`)."""
        return self.lost_tracking.kept

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
            self.odometry.track(index, frame.images, frame.depths if self.exact_depth else None, depth_at=None if self.exact_depth or self.stereo.pairs else self.depth_targets.solved_at_frame)
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
            geometric = self.factors(keyframes, edges)
            if self.jdsa_active:
                stats = mcba_with_jdsa(self.mcba, edges, targets, weights, keyframes=keyframes, rounds=1, hold_mean=not self.metric_edges, keypoints=kp, factors=geometric, fixed=self.held(keyframes), config=config)[-1]
            else:
                stats = self.mcba.solve(edges, targets, weights, keyframes=keyframes, keypoints=kp, factors=geometric, fixed=self.held(keyframes), config=config)
            out.append((stats, float(np.nansum(weights))))
            after = self.buf.get_poses()
            if kp is not None:
                self.tracks.update(kp, roots, list(keyframes), after, self.factors.T_b_c)
            self._events.append(PosesMoved(before, after))
        self._events += self.depth_targets.moved(keyframes, self.seq, self.lost, self.kept)
        return out

    def _keypoint_problem(self, keyframes, poses):
        """The keypoint tracks of ``keyframes`` as an MCBA problem (None without tracks)."""
        if self.tracks is None:
            return None, []
        return self.tracks.problem(list(keyframes), lambda k: self.keyframe_views[k], poses, self.factors.T_b_c, self.depth_targets.solved_at)

    def take_update(self) -> list:
        """The pose and depth changes since the last call, in order (:class:`PosesMoved`,
        :class:`DepthMoved`): what the map must follow. Tracking never touches the map itself."""
        events, self._events = self._events, []
        return events

    def add_keyframe(self, frame) -> KeyframeUpdate:
        """``frame`` as a new keyframe (:meth:`_insert`) and what the map must do about it, in
        order: follow the moves of its solve, then register the keyframes to map with their
        depth targets (:meth:`mapping_depths`) and the grid depth their Gaussians are placed
        with. Bootstrap: without exact depth, keyframe 0 is registered only after keyframe 1's
        MCBA, so that no Gaussian is seeded from the constant start depth. Lost keyframes
        (:attr:`lost`) are not registered."""
        k = self._insert(frame)
        moved = self.take_update()
        new = [k] if self.exact_depth else [0, k] if k == 1 else [] if k == 0 else [k]
        register = [Registration(m, self.mapping_depths(self.seq[self.buf.frame_index[m]], m), self.buf.depth(m)) for m in new if m not in self.lost]
        return KeyframeUpdate(k, moved, register, sliding_window(len(self.buf), self.cfg.tracking.window))

    def _insert(self, frame) -> int:
        """Add ``frame`` to the keyframe buffer at its start (keypoint odometry, keypoint PnP,
        constant velocity or a given pose) with its depth prior, solve the window (MCBA + JDSA)
        and judge the solve's health (recovering from a failure); returns its index."""
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
            views = odo.views[frame.index] if frame.index in odo.views else self.keypoints.detect(frame.images, frame.depths if self.exact_depth else None)
            if len(buf):
                recent = [j for j in range(len(buf)) if j not in self.lost][-self.keypoints.cfg.keyframes :]  # a lost keyframe's pose is only a prediction
                self._anchor = self.keypoints.localize(views, self.keyframe_views, recent, poses, self.depth_targets.solved_at, guess=T_init, solved=self._solved_points)
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
            self.keyframe_views[k] = views
            if self.tracks is not None:
                self.tracks.add_views(k, views)
                if self._anchor is not None:
                    self.tracks.link(k, self._anchor.matches)
        if len(buf) > 1:
            window = sliding_window(len(buf), tc.window)
            self.graph.update_window(window, cross_view=self.overlap is not None)
            lonely = self.graph.link_to_previous(k, len(self.seq.rig))
            if lonely:
                log.warning("keyframe %d: camera(s) %s overlap no view of the window; linked to keyframe %d", k, lonely, k - 1)
            why = self.checks.check(k, self.solve(window, fresh=set(window[-tc.temporal_radius - 1 :])), self._anchor, self.factors.geometric)
            tracked = why is None or self._recover(k, window, T_init, disp, why)
            self.lost_tracking.update(k, int(self.buf.frame_index[k]), tracked)
        return k

    def state_arrays(self, store) -> dict:
        """The tracking stage's state for a checkpoint (:func:`.tracker_state.state_arrays`)."""
        return tracker_state.state_arrays(self, store)

    def load_state_arrays(self, a: dict, store, source) -> None:
        """Restore :meth:`state_arrays` (:func:`.tracker_state.load_state_arrays`)."""
        tracker_state.load_state_arrays(self, a, store, source)

    def close_lost_span(self) -> None:
        """At the end of the run: say that tracking was lost, if a lost span is still open."""
        self.lost_tracking.close_span()

    @property
    def _solved_points(self):
        """World points of keypoint tracks as MCBA solved them (None without tracks)."""
        return self.tracks.world_points if self.tracks is not None else None

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
        if self.keypoints is not None and k in self.keyframe_views:
            others = [j for j in range(len(buf)) if j != k and j not in self.lost]
            reloc = self.keypoints.localize(self.keyframe_views[k], self.keyframe_views, others, buf.get_poses(), self.depth_targets.solved_at, solved=self._solved_points)
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
        second = self.checks.check(k, self.solve(window), self._anchor, self.factors.geometric)
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
        # a lost one (:meth:`LostTracking.update`), whose dropped matches would leave the keyframes
        # after a lost span nothing to other times
        if placed or not self.lost_tracking.carried:
            self.kept.append(k)
        warn(None, f"frame {frame} (keyframe {k}): tracking failure ({why}; again after re-matching: {second}); keyframe {k} keeps {how}")
        return placed

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
