"""The SLAM pipeline's wiring (paper Fig. 3): what the system is made of and the order in
which it runs.

Per rig frame: the keypoint odometry (its motion since the frame before,
:mod:`~mcgs_warp.frontend.keypoint_odometry`), the keyframe test (mean DIS flow since the last
keyframe); for a new keyframe the keyframe step (:mod:`.keyframe_step`: the odometry's or the
constant-velocity start, depth prior, MCBA (+ JDSA)
over the sliding window, tracking health), then mapping of its views and mapping iterations
over the window. Bootstrap: without exact depth, keyframe 0 is mapped only after keyframe 1's
MCBA, so that no Gaussian is seeded from the constant start depth. After the last frame the
offline stage (:mod:`.offline`: global MCBA with long and loop edges, photo-consistent depth
targets, joint refinement). The online state is checkpointed after every keyframe
(:mod:`.checkpoint`). Non-keyframe poses come from the odometry (moved by the keyframes'
correction) or are interpolated between keyframes. Deterministic for a seed.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..ba.edges import GraphConfig, camera_overlap, camera_pairs, sliding_window
from ..ba.graph import FactorGraph
from ..ba.keypoint_tracks import KeypointTracks
from ..ba.mcba import MCBA, MCBAConfig
from ..buffer import KeyframeBuffer
from ..data.sequence import Sequence
from ..data.trajectory import Trajectory
from ..frontend.depth import choose_prior
from ..frontend.flow import DISFlow, GuidedDIS, GuidedOrRaw, NoCorrespondences, SequenceGroundTruthFlow, StereoMatches
from ..frontend.keyframes import KeyframeSelector
from ..frontend.keypoint_odometry import KeypointOdometry
from ..frontend.keypoint_tracker import KeypointTracker
from ..frontend.stereo import RigStereo
from ..geometry import matrix_to_quat, quat_to_matrix
from ..mapping.gaussian_map import GaussianMap
from ..mapping.mapper import Mapper
from .checkpoint import Checkpointing
from .config import RunConfig
from .keyframe_step import KeyframeStep
from .offline import OfflineStage


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


class SLAM(KeyframeStep, OfflineStage, Checkpointing):
    """The system: its parts (below) and the loop over the frames (:meth:`run`)."""

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
        self.oracle = SequenceGroundTruthFlow(sequence) if tc.correspondences == "ground-truth" else NoCorrespondences() if tc.correspondences == "none" else None
        if tc.correspondences == "none" and not (tc.keypoints and tc.keypoint_weight > 0):
            from ..errors import InputError

            raise InputError(None, "tracking.correspondences", "none leaves only the keypoint tracks: it needs tracking.keypoints true and tracking.keypoint_weight above 0")
        self.stereo_matches = StereoMatches(self.stereo)
        self.keypoints = KeypointTracker(sequence.rig, rig_overlap, self.stereo.pairs, seed=config.seed) if tc.keypoints else None
        self.odometry = KeypointOdometry(sequence.rig, rig_overlap, self.stereo.pairs, seed=config.seed) if tc.keypoints else None  # every frame's motion
        self.tracks = KeypointTracks(tc.keypoint_weight) if tc.keypoints and tc.keypoint_weight > 0 else None  # keypoint tracks in MCBA
        self.mcba = MCBA(self.buf, MCBAConfig(iterations=tc.mcba_iterations, huber_delta=tc.huber_px, prior_weight=tc.prior_weight if self.prior.metric else 0.0, variance_components=tc.variance_components))
        self.mapper = Mapper(self.buf, GaussianMap(self.buf.device), config.mapping, seed=config.seed)
        self.mapper.sky_depth_veto = self.exact_depth  # a region exact sensor depth measures is not sky
        self.graph = FactorGraph(self.buf, self.overlap, GraphConfig(max_per_view=2 * tc.temporal_radius))  # edges and their correspondences
        self.loops: list = []  # LoopCheck of every revisit candidate global BA examined
        self._mapped_depth: dict = {}  # keyframe -> grid depth [C,h,w] its Gaussians were last placed with
        self.seconds = {"tracking": 0.0, "mapping": 0.0, "refinement": 0.0}
        self.frame_motion: dict = {}  # frame index -> image motion (rad) since the frame before it (the keyframe test's flows, :func:`motion`)
        self._anchor = None  # the newest keyframe's keypoint pose (PnPResult) or None
        self._geometric, self._grid = None, None  # the last solve's depth-alignment factors (window, factors); grid rays and cameras for them
        self.lost: list = []  # keyframes whose tracking was lost (:meth:`_track_state`): not mapped
        self.kept: list = []  # keyframes whose dense solve failed twice where keypoints placed them: MCBA holds their keypoint pose and drops their temporal correspondences from then on (:meth:`_recover`)
        self._carried, self._lost_span = False, None  # the last keyframe kept the constant-velocity prediction; the open lost span [first frame, last frame, keyframes]
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
            if self.odometry is not None:
                self.odometry.track(idx, frame.images, frame.depths if self.exact_depth else None, depth_at=None if self.exact_depth or self.stereo.pairs else self._frame_depth)
            is_kf = last_images is None
            if not is_kf:  # the keyframe test's flows also tell whether the rig stood still since the frame before
                is_kf, self.frame_motion[idx] = self.selector.is_keyframe(last_images, frame.images)
                is_kf = is_kf or idx == n - 1
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
                if m in self.lost:
                    continue
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
        self.close_lost_span()
        self.refine()
        traj = self.trajectory(kf_frames)
        curve = [(i, r.loss, r.psnr) for i, r in enumerate(self.mapper.history)]
        return RunResult(traj, kf_frames, curve, dict(self.seconds))

    def given_pose(self, index: int):
        """A pose given for frame ``index`` (:class:`~mcgs_warp.system.posed_mapping.PosedMapping`), else None."""
        return None

    def held(self, keyframes):
        """Keyframes whose poses MCBA holds: the first of the window (the gauge) and those kept
        at their keypoint pose after a failed dense solve (:attr:`kept`); None: the gauge alone."""
        kept = [int(k) for k in keyframes if k in self.kept]
        return {int(keyframes[0]), *kept} if kept else None

    def _filler(self, fa: int, fb: int):
        """Poses [frame -> 4x4] that place the frames between keyframes at frames ``fa`` and
        ``fb`` (:meth:`trajectory`): the keypoint odometry's where it placed every frame of
        the span, else None."""
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

    def trajectory(self, kf_frames) -> Trajectory:
        """Rig poses for every frame: keyframes as estimated; a frame between two keyframes
        that the keypoint odometry placed (every frame of the span) is its odometry pose
        moved by the correction of the keyframe poses, ``T_kf (T_kf^odo)^-1``, interpolated
        between the two keyframes in time (DROID-SLAM's trajectory filler does the same with
        its own tracking). Other frames are interpolated between their keyframes (linear
        translation, spherical-linear rotation) in time, except that
        time the rig stood still does not count: a frame whose image motion since the frame
        before (:attr:`frame_motion`) is below :data:`STILL_MOTION` did not move
        (:func:`moving_time`). So a pause stands still, and a drive is plain time
        interpolation (which a car's smooth motion suits: 3 mm off on a straight KITTI
        drive with the true keyframe poses)."""
        T_kf = self.buf.get_poses()
        t_kf = np.array(self.buf.timestamps)
        stamps = np.asarray(self.seq.timestamps, dtype=np.float64)
        out = np.zeros((len(stamps), 4, 4))
        clocks: dict = {}
        fillers: dict = {}  # (fa, fb) -> frame poses that place the frames between (:meth:`_filler`) or None
        for i, t in enumerate(stamps):
            j = int(np.clip(np.searchsorted(t_kf, t), 1, max(len(t_kf) - 1, 1))) if len(t_kf) > 1 else 0
            if len(t_kf) == 1:
                out[i] = T_kf[0]
                continue
            a, b = j - 1, j
            u = float(np.clip((t - t_kf[a]) / max(t_kf[b] - t_kf[a], 1e-12), 0.0, 1.0))
            fa, fb = self.buf.frame_index[a], self.buf.frame_index[b]
            if fa < i < fb and (fa, fb) not in fillers:
                fillers[(fa, fb)] = self._filler(fa, fb)
            src = fillers.get((fa, fb))
            if fa < i < fb and src is not None:
                out[i] = interpolate_pose(T_kf[a] @ np.linalg.inv(src[fa]), T_kf[b] @ np.linalg.inv(src[fb]), u) @ src[i]
                continue
            if fa < i < fb:
                if (fa, fb) not in clocks:  # once per keyframe interval
                    clocks[(fa, fb)] = moving_time(stamps[fa : fb + 1], [self.frame_motion.get(f) for f in range(fa + 1, fb + 1)])
                if clocks[(fa, fb)] is not None:
                    u = float(clocks[(fa, fb)][i - fa])
            out[i] = interpolate_pose(T_kf[a], T_kf[b], u)
        return Trajectory(stamps, out)


#: rad (1.8 px at a 180 px focal length, 3.7 px at KITTI's 370): less image motion since the frame before
#: is a pause. Chosen on indoor seeds 6 and 10 (camera noise in a still, low-texture corridor reaches
#: 0.006 rad; the slowest drive 0.024); KITTI's frames move 0.028 rad or more.
STILL_MOTION = 0.01


def moving_time(stamps, motions, still: float = STILL_MOTION):
    """Fractions [n] of the time from the first to the last of ``stamps`` [n] that the rig
    spent moving, per frame, or None (all frames moved: plain time interpolation; a motion
    is unknown; nothing moved). ``motions`` [n-1]: image motion (rad) of each frame after
    the first since the frame before it; below ``still`` it stood still."""
    if any(m is None for m in motions):
        return None
    moved = np.asarray(motions, np.float64) >= still
    if moved.all() or not moved.any():
        return None
    clock = np.concatenate([[0.0], np.cumsum(np.where(moved, np.diff(np.asarray(stamps, np.float64)), 0.0))])
    return clock / clock[-1]


def interpolate_pose(A: np.ndarray, B: np.ndarray, u: float) -> np.ndarray:
    """The pose [4,4] a fraction ``u`` of the way from ``A`` to ``B``: linear translation,
    spherical-linear rotation."""
    T = np.eye(4)
    T[:3, 3] = (1 - u) * A[:3, 3] + u * B[:3, 3]
    T[:3, :3] = quat_to_matrix(slerp(matrix_to_quat(A[:3, :3]), matrix_to_quat(B[:3, :3]), u))
    return T


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    return (np.sin((1 - u) * th) * q0 + np.sin(u * th) * q1) / np.sin(th)
