"""The online SLAM loop and offline refinement (paper Fig. 3).

Per rig frame: keyframe test (mean DIS flow since the last keyframe); for a new
keyframe: initial pose by constant velocity, depth from the prior, MCBA (+ JDSA)
over the sliding window on the factor graph's edges (views that overlap, and
cross-view edges; JDSA only for inexact, monocular-style priors: rescaling exact
sensor depth would free the metric scale), anchored Gaussians follow the moved
keyframes and, per pixel, their depth changes, new Gaussians where the map is empty,
and mapping iterations. Non-keyframe poses are interpolated between keyframes. After
the last frame: global MCBA over all keyframes with long and confirmed loop edges,
then joint refinement of map, poses and exposures. Deterministic for a seed.
"""

from __future__ import annotations

import logging
import sys
import time
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..ba.edges import TEMPORAL, GraphConfig, camera_overlap, camera_pairs, sliding_window
from ..ba.graph import FactorGraph
from ..ba.jdsa import mcba_with_jdsa, scale_field
from ..ba.mcba import MCBA, MCBAConfig
from ..buffer import KeyframeBuffer
from ..data.sequence import Sequence
from ..data.trajectory import Trajectory
from ..frontend.depth import choose_prior, grid_depth, upsample_inverse_depth_guided
from ..frontend.flow import DISFlow, GuidedDIS, GuidedOrRaw, SequenceGroundTruthFlow, StereoMatches
from ..frontend.stereo import RigStereo
from ..frontend.keyframes import KeyframeSelector
from ..geometry import matrix_to_quat, quat_to_matrix
from ..mapping.gaussian_map import GaussianMap
from ..mapping.mapper import Mapper
from ..mapping.refine import joint_refinement
from .config import RunConfig


GLOBAL_BA_MIN_OVERLAP = 0.1  # long edges need less shared view: guided flow matches what there is
log = logging.getLogger("mcgs_warp.slam")
#: What a checkpoint holds; raise it whenever save_checkpoint's arrays change meaning or names
#: (2: the keyframe buffer's exposures, device priors and JDSA grids; 3: tracking health; 4: the mapping background;
#: 5: per-keyframe depth files beside the checkpoint), so that
#: --resume refuses an older checkpoint by name instead of failing on a missing array.
CHECKPOINT_FORMAT = 5
INITIAL_DEPTH = 3.0  # m: MCBA's start where nothing is known yet (DROID-SLAM starts from a constant too)


class Progress:
    """One status line on stderr: stage, counts and rate."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.t0 = time.perf_counter()
        self.last = 0.0

    def __call__(self, stage: str, done: int, total: int, extra: str = "", force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if not force and not self.tty and now - self.last < 5.0 and done < total:
            return
        self.last = now
        rate = done / max(now - self.t0, 1e-9)
        line = f"[{now - self.t0:7.1f} s] {stage:<10} {done:>4}/{total:<4} ({rate:.2f}/s) {extra}"
        print(("\r" + line.ljust(100)) if self.tty else line, end="" if self.tty else "\n", file=sys.stderr, flush=True)

    def done(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr)


@dataclass
class RunResult:
    trajectory: Trajectory  # rig body T_w_b for every frame
    keyframe_frames: list
    mapping_curve: list = field(default_factory=list)  # (iteration, loss, psnr)
    seconds: dict = field(default_factory=dict)


class SLAM:
    def __init__(self, sequence: Sequence, config: RunConfig, device=None, progress: Progress | None = None):
        self.seq = sequence
        self.cfg = config
        tc = config.tracking
        self.progress = progress or Progress(False)
        self.buf = KeyframeBuffer(sequence.rig, stride=tc.stride, capacity=len(sequence) + 1, device=device)
        rig_overlap = camera_overlap(sequence.rig, stride=tc.stride)
        self.stereo = RigStereo(sequence.rig, rig_overlap, device=self.buf.device)
        self.prior = choose_prior(sequence, tc.depth, lambda: self.stereo if self.stereo.pairs else None)
        # Correspondences: where they measure depth, full-resolution DIS with small patches (RGB
        # only, seed 1: depth L1 0.206 -> 0.137 m); with exact sensor depth they only constrain
        # the poses, and the preset (half resolution) is 3.7x cheaper per call (the demo: SE(3)
        # ATE 2.54 vs 2.31 mm, 60 vs 74-78 s of SLAM time).
        self.flow = DISFlow() if self.exact_depth else DISFlow(finest_scale=0, patch_size=4, smoothness=5.0)
        self.guided = GuidedDIS(self.flow)
        self.guided_or_raw = GuidedOrRaw(self.guided, self.flow)
        self.selector = KeyframeSelector(DISFlow(), sequence.rig.cameras, threshold=tc.keyframe_flow)  # a mean flow: half resolution is enough
        # Cross-view edges (eq. 8) constrain only depth; exact sensor depth already fixes it,
        # so with it they cost their sweeps and change nothing (demo: 4.3 vs 4.5 mm SE(3) ATE).
        self.overlap = rig_overlap if tc.cross_view and not self.exact_depth else None
        self.oracle = SequenceGroundTruthFlow(sequence) if tc.correspondences == "ground-truth" else None
        self.stereo_matches = StereoMatches(self.stereo)
        self.mcba = MCBA(self.buf, MCBAConfig(iterations=tc.mcba_iterations, huber_delta=tc.huber_px, prior_weight=tc.prior_weight if self.prior.metric else 0.0))
        self.mapper = Mapper(self.buf, GaussianMap(self.buf.device), config.mapping, seed=config.seed)
        self.graph = FactorGraph(self.buf, self.overlap, GraphConfig(max_per_view=2 * tc.temporal_radius))  # edges and their correspondences
        self.loops: list = []  # LoopCheck of every revisit candidate global BA examined
        self._mapped_depth: dict = {}  # keyframe -> grid depth [C,h,w] its Gaussians were last placed with
        self.seconds = {"tracking": 0.0, "mapping": 0.0, "refinement": 0.0}
        self.health: list = []  # per keyframe solve (a recovered keyframe has two): frame, confident fraction, residual level, accepted steps, failure (why, or None)
        if not self.metric_scale:
            from ..data.sequence import warn

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

    # ----------------------------------------------------------------------------------
    def measure(self, refresh=(), guided_new: bool = False) -> None:
        """Correspondences for the graph's active edges that have none: cross-view edges from
        the rig's sweep stereo, the others from DIS; edges touching a keyframe in ``refresh``
        are re-estimated from the current reprojection (:class:`GuidedDIS`) unless the current
        geometry already predicts their matches (:meth:`GuidedDIS.settled`); ``guided_new``
        computes new non-cross-view edges that way from the start (global BA's long edges:
        their keyframes are already solved, their motion too large for raw DIS), and so does
        exact sensor depth (its prediction is good from the first solve on). With
        ``--correspondences ground-truth`` every edge is exact (oracle)."""
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
            # by plain DIS where the start is too poor to guide
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
            before = self.buf.get_poses()
            if self.jdsa_active:
                stats = mcba_with_jdsa(self.mcba, edges, targets, weights, keyframes=keyframes, rounds=1, hold_mean=not self.metric_edges)[-1]
            else:
                stats = self.mcba.solve(edges, targets, weights, keyframes=keyframes)
            out.append((stats, float(np.nansum(weights))))
            self.mapper.map.follow_keyframes(before, self.buf.get_poses())
        self._follow_depths(keyframes)
        return out

    def _confident_fraction(self, k: int) -> float:
        """Fraction of keyframe ``k``'s grid pixels (all cameras) with a confident (weight >
        0.5) correspondence to another keyframe."""
        rows = [n for n, e in enumerate(self.graph.edges) if e[0] == k and e[2] != k]
        if not rows:
            return 0.0
        edges = self.graph.edges[rows]
        _, w = self.graph.correspondences(edges)
        linked = np.zeros((len(self.seq.rig), self.buf.h, self.buf.w), bool)
        for e, wt in zip(edges, w):
            linked[int(e[1])] |= wt > 0.5
        area = sum((c.height // self.buf.stride) * (c.width // self.buf.stride) for c in self.seq.rig.cameras)
        return float(linked.sum()) / max(area, 1)

    def _health(self, k: int, rounds: list) -> str | None:
        """Why the solve that added keyframe ``k`` is a tracking failure, or None: no MCBA
        step accepted in any round, too few confident correspondences, or a final robust cost
        per unit of correspondence weight far above the run's usual level."""
        th = self.cfg.tracking
        frac = self._confident_fraction(k)
        stats, weight = rounds[-1]
        level = stats.cost[-1] / max(weight, 1e-9) if stats.cost else float("nan")
        healthy = [h["residual"] for h in self.health if not h["failure"] and np.isfinite(h["residual"])]
        usual = float(np.median(healthy)) if len(healthy) >= 3 else None
        why = None
        if all(st.accepted == 0 for st, _ in rounds) and any(st.cost for st, _ in rounds):
            why = "no MCBA step accepted"
        elif frac < th.min_confident:
            why = f"only {100 * frac:.1f} % of its pixels have a confident correspondence (tracking.min_confident {100 * th.min_confident:g} %)"
        elif usual is not None and np.isfinite(level) and level > th.max_residual_ratio * usual:
            why = f"residual {level:.3g} is {level / usual:.0f}x the run's median (tracking.max_residual_ratio {th.max_residual_ratio:g})"
        self.health.append({"keyframe": k, "frame": int(self.buf.frame_index[k]), "confident": round(frac, 4), "residual": float(level), "accepted": int(sum(st.accepted for st, _ in rounds)), "failure": why})
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
        if len(buf) > 1:
            window = sliding_window(len(buf), tc.window)
            self.graph.update_window(window, cross_view=self.overlap is not None)
            self._link_newest(k)
            why = self._health(k, self._solve(window, fresh=set(window[-tc.temporal_radius - 1 :])))
            if why is not None:
                self._recover(k, window, T_init, disp, why)
        return k

    def _recover(self, k: int, window, T_init: np.ndarray, disp0: np.ndarray, why: str) -> None:
        """A tracking failure at keyframe ``k``: one warning line, then re-initialize it from
        the constant-velocity prediction (pose ``T_init``, start depth ``disp0``), drop its
        correspondences and match them again from that prediction (guided by the older
        keyframes' solved depth, plain DIS where the prediction cannot guide), and solve
        again. If that fails too, ``k`` keeps the prediction."""
        from ..data.sequence import warn

        buf = self.buf
        frame = buf.frame_index[k]
        buf.set_poses(T_init[None], start=k)
        buf.disp[k].assign(np.asarray(disp0, dtype=np.float32))
        own = np.array([e for e in self.graph.edges if (e[0] == k) != (e[2] == k)], np.int32).reshape(-1, 5)  # k's edges to other keyframes
        self.graph.forget(own)
        self.graph.add(own)
        self.graph.compute(self.guided_or_raw, self.graph.missing())
        second = self._health(k, self._solve(window))
        if second is None:
            warn(None, f"frame {frame} (keyframe {k}): tracking failure ({why}); recovered from the constant-velocity prediction")
            return
        buf.set_poses(T_init[None], start=k)
        warn(None, f"frame {frame} (keyframe {k}): tracking failure ({why}; again after re-matching: {second}); keyframe {k} keeps the constant-velocity prediction")

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

    def _measured_weight(self, keyframes) -> dict:
        """Per keyframe [C,h,w]: summed correspondence confidence of every edge (active or
        stored) leaving each of its grid pixels (:meth:`FactorGraph.measured_weight`)."""
        return {k: self.graph.measured_weight(k, len(self.seq.rig)) for k in set(keyframes)}

    def _constrained(self, k: int, weight: np.ndarray) -> np.ndarray:
        """[C,h,w] bool: grid pixels of keyframe k whose depth something measured (confident
        correspondences from the view, ``weight`` from :meth:`_measured_weight`, or a confident prior)."""
        total = (self.buf.prior_conf[k].numpy() > 0.5) if self.prior.metric else np.zeros(weight.shape, bool)
        return total | (weight >= 1.0)

    # ----------------------------------------------------------------------------------
    def save_checkpoint(self, path, next_frame: int, kf_frames: list) -> None:
        """Write the whole online state atomically (``path``: a .npz file). The large parts
        live beside it and are written only when they change, so a run's checkpoint I/O grows
        with the keyframes, not with their square: the factor graph's correspondences in
        segment files (:func:`correspondence_store`), each mapped keyframe's full-resolution
        depth targets and placement depth in a file named by its content (:func:`keyframe_store`)."""
        import json

        from ..io import atomic_write

        buf, K = self.buf, len(self.buf)
        arrays = {f"mapper.{k}": v for k, v in self.mapper.state_arrays().items()}
        arrays.update(
            poses=buf.poses.numpy()[:K].copy(),
            disp=buf.disp.numpy()[:K].copy(),
            depth_prior=buf.depth_prior[:K].numpy().copy(),
            prior_conf=buf.prior_conf[:K].numpy().copy(),
            scales=buf.scales[:K].numpy().copy(),
            exposure=buf.exposure.numpy()[:K].copy(),
            timestamps=np.array(buf.timestamps),
            frame_index=np.array(buf.frame_index, dtype=np.int64),
            kf_frames=np.array(kf_frames, dtype=np.int64),
            **self.graph.state_arrays(correspondence_store(path)),
            mapped_keys=np.array(sorted(self._mapped_depth), dtype=np.int64),
            keyframe_files=np.array(self._save_keyframe_files(keyframe_store(path)), dtype=str).reshape(-1),
            meta=np.array(json.dumps({"format": CHECKPOINT_FORMAT, "next_frame": next_frame, "config": self.cfg.to_dict(), "n_frames": len(self.seq), "seconds": self.seconds, "health": self.health})),
        )
        with atomic_write(path, "wb") as f:
            np.savez(f, **arrays)
        self.graph.prune_store(correspondence_store(path))  # segments only the replaced checkpoint used
        keep = set(arrays["keyframe_files"].tolist())
        for old in keyframe_store(path).glob("kf*.npz"):
            if old.name not in keep:
                old.unlink(missing_ok=True)

    def _save_keyframe_files(self, store: Path) -> list:
        """One file per mapped keyframe (``kf<k>_<content digest>.npz``: ``targets_cam<c>``,
        the full-resolution mapping depth targets, none for exact sensor depth, which is
        re-read; ``mapped_depth`` [C,h,w]); a file already there is not written again."""
        import hashlib

        from ..io import atomic_write

        store.mkdir(parents=True, exist_ok=True)
        names = []
        for k in sorted(self._mapped_depth):
            arrays = {f"targets_cam{c}": np.asarray(self.buf.targets[k][c] if not self.exact_depth else np.zeros(0), np.float32) for c in range(len(self.seq.rig))}
            arrays["mapped_depth"] = np.asarray(self._mapped_depth[k], np.float64)
            digest = hashlib.blake2b(digest_size=10)
            for v in arrays.values():
                digest.update(np.ascontiguousarray(v).tobytes())
            name = f"kf{k:05d}_{digest.hexdigest()}.npz"
            if not (store / name).is_file():
                with atomic_write(store / name, "wb") as f:
                    np.savez(f, **arrays)
            names.append(name)
        return names

    def load_checkpoint(self, path) -> tuple[int, list]:
        """Restore the state saved by :meth:`save_checkpoint`; returns (next frame, keyframe frames)."""
        import json

        import warp as wp

        from ..errors import InputError

        try:
            with np.load(path, allow_pickle=False) as z:
                a = {k: z[k] for k in z.files}
            meta = json.loads(str(a["meta"]))
        except (OSError, ValueError, KeyError) as e:
            raise InputError(path, None, f"unreadable checkpoint ({e})") from None
        if meta.get("format") != CHECKPOINT_FORMAT:
            raise InputError(path, None, f"checkpoint was written by an older version (format {meta.get('format', 1)}, this version reads {CHECKPOINT_FORMAT}); start without --resume")
        if meta["config"] != self.cfg.to_dict() or meta["n_frames"] != len(self.seq):
            raise InputError(path, None, "checkpoint was written by a run with another configuration or sequence; start without --resume")
        try:  # the format is the current one: a missing array means a damaged file
            buf = self.buf
            for k, fi in enumerate(a["frame_index"]):
                frame = self.seq[int(fi)]
                buf.add(int(fi), float(a["timestamps"][k]), frame.images, np.eye(4), a["disp"][k], depth_prior=a["depth_prior"][k], prior_conf=a["prior_conf"][k])
            wp.copy(buf.poses, wp.array(a["poses"], dtype=wp.transform, device=buf.device), count=len(a["poses"]))
            grids = buf.scales.numpy()
            grids[: len(a["scales"])] = a["scales"]
            buf.scales.assign(grids)
            exposure = buf.exposure.numpy()
            exposure[: len(a["exposure"])] = a["exposure"][: len(exposure)]
            buf.exposure.assign(exposure)
            try:
                self.graph.load_state_arrays(a, correspondence_store(path))
            except (OSError, ValueError, KeyError, IndexError, EOFError, zipfile.BadZipFile) as e:
                raise InputError(correspondence_store(path), None, f"unreadable checkpoint correspondences ({e}); start without --resume") from None
            try:
                files = {}
                for k, name in zip(a["mapped_keys"], a["keyframe_files"]):
                    with np.load(keyframe_store(path) / str(name), allow_pickle=False) as z:
                        files[int(k)] = {n: z[n] for n in z.files}
            except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
                raise InputError(keyframe_store(path), None, f"unreadable checkpoint keyframe file ({e}); start without --resume") from None
            self._mapped_depth = {k: f["mapped_depth"] for k, f in files.items()}
            if not self.exact_depth:  # estimated targets: restore them as they were
                depths = {k: [f[f"targets_cam{c}"] for c in range(len(self.seq.rig))] for k, f in files.items()}
            else:
                depths = {k: self.mapping_depths(self.seq[int(fi)], k) for k, fi in enumerate(a["frame_index"])}
            self.mapper.load_state_arrays({k[7:]: v for k, v in a.items() if k.startswith("mapper.")}, depths)
            self.seconds = meta["seconds"]
            self.health = meta["health"]
            kf_frames = [int(v) for v in a["kf_frames"]]
        except KeyError as e:
            raise InputError(path, None, f"unreadable checkpoint (no array {e}); start without --resume") from None
        return int(meta["next_frame"]), kf_frames

    def run(self, checkpoint=None, resume: bool = False, stop_after_keyframes: int | None = None) -> RunResult:
        """Process every frame, then refine. With ``checkpoint`` (a .npz path) the state is
        saved after each keyframe; ``resume`` continues from it. ``stop_after_keyframes``
        simulates an interruption (tests)."""
        n = len(self.seq)
        kf_frames, last_images, start = [], None, 0
        if resume and checkpoint is not None and Path(checkpoint).is_file():
            start, kf_frames = self.load_checkpoint(checkpoint)
            last_images = self.seq[kf_frames[-1]].images if kf_frames else None
            self.progress("resumed", start, n, f"keyframes {len(kf_frames)}", force=True)
        mcfg = self.cfg.mapping
        for idx in range(start, n):
            frame = self.seq[idx]
            t0 = time.perf_counter()
            is_kf = last_images is None or idx == n - 1
            if not is_kf:
                is_kf, _ = self.selector.is_keyframe(last_images, frame.images)
            if not is_kf:
                self.seconds["tracking"] += time.perf_counter() - t0
                self.progress("tracking", idx + 1, n, f"keyframes {len(kf_frames)}")
                continue
            k = self.add_keyframe(frame)
            kf_frames.append(idx)
            last_images = frame.images
            t1 = time.perf_counter()
            # Bootstrap: without exact depth, keyframe 0 waits for the MCBA of keyframe 1,
            # so that no Gaussian is seeded from the constant start depth.
            for m in ([0, k] if k == 1 and not self.exact_depth else [] if k == 0 and not self.exact_depth else [k]):
                self.mapper.add_keyframe(m, self.mapping_depths(self.seq[self.buf.frame_index[m]], m))
                self._mapped_depth[m] = self.buf.depth(m)
            window = sliding_window(len(self.buf), self.cfg.tracking.window)
            if self.buf.targets:
                self.mapper.optimize(mcfg.iterations_per_keyframe, keyframes=[w for w in window if w in self.buf.targets])
            t2 = time.perf_counter()
            self.seconds["tracking"] += t1 - t0
            self.seconds["mapping"] += t2 - t1
            if checkpoint is not None:
                self.save_checkpoint(checkpoint, idx + 1, kf_frames)
            if stop_after_keyframes is not None and len(kf_frames) >= stop_after_keyframes:
                raise KeyboardInterrupt(f"stopped after {len(kf_frames)} keyframes")
            psnr = self.mapper.history[-1].psnr if self.mapper.history else float("nan")
            self.progress("tracking", idx + 1, n, f"keyframes {len(kf_frames)}  gaussians {len(self.mapper.map)}  psnr {psnr:.1f} dB")
        self.progress.done()
        self.refine()
        traj = self.trajectory(kf_frames)
        curve = [(i, r.loss, r.psnr) for i, r in enumerate(self.mapper.history)]
        return RunResult(traj, kf_frames, curve, dict(self.seconds))

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

    def trajectory(self, kf_frames) -> Trajectory:
        """Rig poses for every frame: keyframes as estimated, others interpolated in time
        (linear translation, spherical-linear rotation)."""
        T_kf = self.buf.get_poses()
        t_kf = np.array(self.buf.timestamps)
        stamps = np.asarray(self.seq.timestamps, dtype=np.float64)
        out = np.zeros((len(stamps), 4, 4))
        q_kf = matrix_to_quat(T_kf[:, :3, :3])
        for i, t in enumerate(stamps):
            j = int(np.clip(np.searchsorted(t_kf, t), 1, max(len(t_kf) - 1, 1))) if len(t_kf) > 1 else 0
            if len(t_kf) == 1:
                out[i] = T_kf[0]
                continue
            a, b = j - 1, j
            u = float(np.clip((t - t_kf[a]) / max(t_kf[b] - t_kf[a], 1e-12), 0.0, 1.0))
            out[i] = np.eye(4)
            out[i, :3, 3] = (1 - u) * T_kf[a, :3, 3] + u * T_kf[b, :3, 3]
            out[i, :3, :3] = quat_to_matrix(slerp(q_kf[a], q_kf[b], u))
        return Trajectory(stamps, out)


def depth_ratio(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Per-pixel ``new / old`` [C,h,w] of two grid depths (1 where either is unknown),
    3x3-median filtered (one noisy pixel moves no Gaussian) and clipped to [0.5, 2]."""
    import cv2

    ok = (old > 0) & (new > 0)
    r = np.where(ok, new / np.where(ok, old, 1.0), 1.0).astype(np.float32)
    return np.clip(np.stack([cv2.medianBlur(x, 3) for x in r]), 0.5, 2.0)


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    return (np.sin((1 - u) * th) * q0 + np.sin(u * th) * q1) / np.sin(th)


def keyframe_store(checkpoint) -> Path:
    """The folder beside a checkpoint ``.npz`` that holds its per-keyframe files
    (``out/checkpoint.npz`` -> ``out/checkpoint.keyframes/``)."""
    return Path(checkpoint).with_suffix(".keyframes")


def correspondence_store(checkpoint) -> Path:
    """The folder beside a checkpoint ``.npz`` that holds its correspondence segments
    (``out/checkpoint.npz`` -> ``out/checkpoint.corr/``)."""
    return Path(checkpoint).with_suffix(".corr")
