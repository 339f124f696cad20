"""Keypoint odometry: the rig pose of *every* frame from keypoints, as a classical stereo VO.

Keyframes are a few frames apart; at highway speed that is metres, where keypoint and dense
matches both thin out. Frame to frame the motion is small and the matches are many. So every
frame's keypoints (:mod:`.keypoints`) are matched against the last ``frames`` frames and
placed by the multi-camera PnP (:mod:`.pnp`, constant velocity as a hypothesis and the
fallback), their PnP inliers join keypoint tracks (:class:`~mcgs_warp.ba.keypoint_tracks.KeypointTracks`),
and a sliding-window bundle adjustment over the last ``window`` frames (the tracks' reprojection
factors, :class:`~mcgs_warp.ba.keypoint_factors.KeypointFactors`, Levenberg-Marquardt as MCBA's,
:mod:`mcgs_warp.ba.lm`, the oldest pose held) refines poses and points. A keypoint's 3D point comes from what the rig
measures (stereo between overlapping cameras, sensor depth), from its track as solved, or
from the caller's ``depth_at`` (the SLAM's solved keyframe depth: a monocular rig). Where PnP
finds no pose on a rig with few 3D keypoints, the rig's two-view motion (:mod:`.rig_motion`)
places the frame, and the window keeps that step as a factor.

What it gives the SLAM (:mod:`mcgs_warp.system.slam`): the motion between two frames,
:meth:`KeypointOdometry.relative`, with its covariance from the window's information
(:meth:`KeypointOdometry.relative_covariance`, metres and radians: the information times the
tracks' measured variance), which starts a new
keyframe, ties consecutive keyframes in MCBA (:class:`~mcgs_warp.ba.pose_factors.RelativePoseFactors`)
and places the frames between keyframes. Poses live in the odometry's own world frame
(the first frame's rig pose); only relative motion leaves this module.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from ..ba.keypoint_factors import KeypointFactors
from ..ba.lm import damped_step, minimize
from ..ba.pose_factors import RelativePoseFactors
from ..ba.keypoint_tracks import KeypointTracks
from ..data.trajectory import Trajectory
from ..kernels.camera import FAR
from ..geometry import adjoint, invert, se3_exp
from ..rig import Rig
from .keypoint_tracker import KeypointConfig, KeypointTracker
from .rig_motion import rig_motion


@dataclass
class OdometryConfig:
    frames: int = 3  # match a new frame against this many previous frames
    window: int = 5  # frames in the sliding-window bundle adjustment
    iterations: int = 5  # LM iterations per frame
    stride: int = 8  # residual unit: full-resolution px / stride (MCBA's grid pixels)
    huber_px: float = 1.0  # full-resolution px: Huber threshold of the keypoint residuals (keypoints are localized to a pixel; the dense grid's 1 grid px would be 8 here)


@dataclass
class OdometryStep:
    T_w_b: np.ndarray  # [4,4] in the odometry's world frame
    tracked: bool  # placed by keypoints (False: constant velocity carried it)
    inliers: int = 0


class KeypointOdometry:
    def __init__(self, rig: Rig, overlap=None, stereo_pairs=(), config: OdometryConfig | None = None, keypoints: KeypointConfig | None = None, seed: int = 0, tracker: KeypointTracker | None = None):
        """``tracker``: the keypoint tracker to share (the system's tracker matches its keyframes
        with the same one); None builds one from ``overlap``, ``stereo_pairs``, ``keypoints`` and ``seed``."""
        self.cfg = config or OdometryConfig()
        self.rig = rig
        self.tracker = tracker if tracker is not None else KeypointTracker(rig, overlap, stereo_pairs, keypoints, seed=seed)
        self.views: dict = {}  # frame -> its keypoints per camera (the last ``frames`` + ``window`` frames are kept)
        self.tracks = KeypointTracks(1.0)
        self.T_b_c = np.stack([c.T_b_c for c in rig.cameras])
        self.frames: list[int] = []  # frame indices in the order tracked
        self.poses: dict[int, np.ndarray] = {}  # frame -> T_w_b (odometry world)
        self.tracked: dict[int, bool] = {}  # frame -> placed by keypoints
        self.step_cov: dict[int, np.ndarray] = {}  # frame -> [6,6] covariance of the step from the frame before (right perturbation of T_prev^-1 T_frame)
        self.two_view: dict[int, np.ndarray] = {}  # frame -> [4,4] its step from the frame before, measured by their 2D-2D matches (:func:`.rig_motion.rig_motion`)

    def track(self, index: int, images, depths=None, depth_at=None) -> OdometryStep:
        """Place frame ``index`` (after every earlier one). ``depths``: exact sensor depth
        per camera or None; ``depth_at(frame, c, uv)`` -> depth [M] (m, 0 unknown) for
        earlier frames' keypoints without their own depth."""
        views = self.tracker.detect(images, depths)
        prev = self.frames[-self.cfg.frames :]
        P = self.poses
        if not prev:
            T, res = np.eye(4), None
        else:
            a = P[prev[-1]]
            guess = a if len(prev) < 2 else a @ invert(P[prev[-2]]) @ a  # constant velocity
            res = self.tracker.localize(views, self.views, prev, P, depth_at, guess=guess, solved=self.tracks.world_points)  # poses by frame: a dict serves
            T = res.T_w_b if res is not None else guess
            kc = self.tracker.cfg
            if res is None and sum(int(v.has_depth.sum()) for v in self.views[prev[-1]]) < kc.min_inliers * len(self.rig):
                # PnP had little to stand on (fewer 3D points per camera, on average, than a pose needs: a surround
                # rig's few overlapping pixels): the 2D-2D matches' metric motion. Where keypoints have
                # depth and PnP still found no pose, constant velocity stays (KITTI every 3rd frame:
                # the two-view step there was 6 % long, constant velocity 4 %)
                two_view = rig_motion(self.views[prev[-1]], views, self.rig, self.tracker.partners, kc.ratio, kc.inlier_rad, kc.min_inliers)
                if two_view is not None:
                    T = a @ two_view.T_a_b
                    self.step_cov[index] = two_view.cov
                    self.two_view[index] = two_view.T_a_b
        self.frames.append(index)
        P[index] = T
        self.tracked[index] = res is not None or not prev or index in self.two_view
        self.views[index] = views
        self.tracks.add_views(index, views)
        if res is not None:
            self.tracks.link(index, res.matches)
        if prev:
            self.adjust(depth_at)
        self._forget()
        return OdometryStep(P[index], self.tracked[index], 0 if res is None else res.n_inliers)

    def adjust(self, depth_at) -> None:
        """LM over the last ``window`` frames' poses and tracks (the oldest held), then the
        newest step's covariance from the window's information (:meth:`track` runs it after
        each frame; ``depth_at`` as there, None: the keypoints' own depth alone)."""
        cfg = self.cfg
        window = self.frames[-cfg.window :]
        poses_of = self.poses
        prob, roots = self.tracks.problem(window, lambda k: self.views[k], poses_of, self.T_b_c, depth_at)
        n = len(window)
        new = window[-1]
        if prob is None:
            return
        f = KeypointFactors(prob, self.rig, cfg.stride, cfg.huber_px / cfg.stride, 1.0 / FAR)
        Pw = np.stack([poses_of[k] for k in window])
        sigma2 = self._tracks_variance(f, Pw)
        steps = self.two_view_factors(window, sigma2)
        free = np.arange(6, 6 * n)
        Pc = None

        def linearize(lam):
            S, rhs = f.reduced_terms(Pw, lam)
            if len(steps):
                S2, rhs2 = steps.reduced_terms(Pw, lam)
                S, rhs = S + S2, rhs + rhs2
            return S, rhs

        def propose(lin, lam):
            nonlocal Pc
            dx = damped_step(*lin, free, lam)
            if not np.all(np.isfinite(dx)):
                return None
            f.candidate(dx)
            Pc = np.stack([Pw[s] @ se3_exp(dx[6 * s : 6 * s + 6]) for s in range(n)])
            return f.cost(Pc, f.disp_c) + steps.cost(Pc)

        def accept(cost, new_cost):
            nonlocal Pw
            Pw = Pc
            f.accept()

        minimize(f.cost(Pw) + steps.cost(Pw), linearize, propose, accept, cfg.iterations)
        for s, k in enumerate(window):
            poses_of[k] = Pw[s]
        prob.disp[:] = f.disp
        self.tracks.update(prob, roots, window, poses_of, self.T_b_c)
        if self.tracked[new] and new not in self.two_view:  # a two-view step keeps its own covariance: few window tracks observe it
            self.step_cov[new] = self.step_covariance(f, Pw, steps)

    def _tracks_variance(self, f: KeypointFactors, Pw: np.ndarray) -> float:
        """The variance the window's keypoint residuals measure (grid px^2,
        :func:`~mcgs_warp.ba.variance.robust_variance`, the window's poses and points as the
        unknowns; 1 when too few residuals measure it): the tracks' cost is written in unit
        weights, so absolute information is multiplied by it to join them, and their own
        information divided by it to become absolute."""
        n = len(Pw)
        noise = f.noise(Pw)
        return 1.0 if noise is None or noise.redundancy <= 6 * (n - 1) else noise.sigma2 * noise.redundancy / (noise.redundancy - 6 * (n - 1))

    def two_view_factors(self, window, sigma2: float) -> RelativePoseFactors:
        """The window's two-view steps (a frame and the one before it; the window is the last
        frames in order) as relative-pose factors: no track links a two-view frame to the frames
        before it, so without its measured step the window holds it by the few tracks later
        frames add and may turn it freely (a rendered street: 10-64 degrees at the next frame).
        Their covariance (m, rad) joins the tracks' unit-weight cost times the tracks' variance
        ``sigma2`` (:meth:`_tracks_variance`), and so does the Huber threshold (3 of the step's
        own standard deviations, as in MCBA)."""
        pairs = [(s - 1, s) for s in range(1, len(window)) if window[s] in self.two_view and window[s] in self.step_cov]
        motions = [self.two_view[window[b]] for _a, b in pairs]
        info = [sigma2 * np.linalg.pinv(self.step_cov[window[b]]) for _a, b in pairs]
        return RelativePoseFactors(pairs, motions, info, huber=3.0 * np.sqrt(sigma2))

    def step_covariance(self, f: KeypointFactors, Pw: np.ndarray, steps: RelativePoseFactors | None = None) -> np.ndarray:
        """[6,6] covariance of the newest step ``T_prev^-1 T_new`` (right perturbation), from
        the inverse of the window's reduced information (oldest pose held; the keypoint
        observations' Huber weights, and the two-view steps that hold the frames before it)
        times the variance the tracks' residuals measure (:meth:`_tracks_variance`): absolute
        units, as MCBA's class weights need."""
        n = len(Pw)
        S = f.reduced_terms(Pw, 0.0)[0]
        if steps is not None and len(steps):
            S = S + steps.reduced_terms(Pw, 0.0)[0]
        S = S[6:, 6:]
        sigma2 = self._tracks_variance(f, Pw)
        try:
            cov = np.linalg.inv(S + 1e-9 * np.eye(len(S)))
        except np.linalg.LinAlgError:
            return np.full((6, 6), np.inf)
        J = np.zeros((6, 6 * (n - 1)))
        J[:, -6:] = np.eye(6)
        if n > 2:  # the previous pose is free too: d(T_prev^-1 T_new) = -Ad(T_step^-1) xi_prev + xi_new
            J[:, -12:-6] = -adjoint(invert(invert(Pw[-2]) @ Pw[-1]))
        return sigma2 * (J @ cov @ J.T)

    @property
    def recent(self) -> list:
        """The frames whose keypoints are kept: those a new frame is matched against or adjusted with."""
        return self.frames[-max(self.cfg.frames, self.cfg.window) :]

    def _forget(self) -> None:
        """Drop keypoints (and track nodes) of frames no new frame will match or adjust again."""
        keep = set(self.recent)
        for k in [k for k in self.views if k not in keep]:
            del self.views[k]
        self.tracks.retain(keep)

    def state_arrays(self) -> dict:
        """The odometry as arrays for a checkpoint: every frame's pose, whether keypoints
        placed it and its step covariance (NaN: none), and the recent frames' tracks (their
        keypoints are detected again on resume, :meth:`load_state_arrays`)."""
        f = np.array(self.frames, np.int64)
        cov = np.stack([self.step_cov.get(int(i), np.full((6, 6), np.nan)) for i in f]) if len(f) else np.zeros((0, 6, 6))
        return {"odometry.frames": f, "odometry.poses": np.stack([self.poses[int(i)] for i in f]) if len(f) else np.zeros((0, 4, 4)),
                "odometry.tracked": np.array([self.tracked[int(i)] for i in f], bool), "odometry.step_cov": cov,
                "odometry.two_view": np.array(sorted(self.two_view), np.int64),
                "odometry.two_view_steps": np.stack([self.two_view[i] for i in sorted(self.two_view)]) if self.two_view else np.zeros((0, 4, 4)),
                **self.tracks.state_arrays("odometry.tracks.")}

    def load_state_arrays(self, a: dict, views_of) -> None:
        """Restore :meth:`state_arrays`; ``views_of(frame)`` detects a recent frame's keypoints again."""
        self.frames = [int(i) for i in a["odometry.frames"]]
        self.poses = {i: T for i, T in zip(self.frames, a["odometry.poses"])}
        self.tracked = {i: bool(t) for i, t in zip(self.frames, a["odometry.tracked"])}
        self.step_cov = {i: c for i, c in zip(self.frames, a["odometry.step_cov"]) if np.all(np.isfinite(c))}
        self.two_view = {int(i): T for i, T in zip(a["odometry.two_view"], a["odometry.two_view_steps"], strict=True)}
        for i in self.recent:
            views = views_of(i)
            self.views[i] = views
            self.tracks.add_views(i, views)
        self.tracks.load_state_arrays(a, "odometry.tracks.")

    def trajectory(self, timestamps) -> Trajectory | None:
        """Its own trajectory (rig body ``T_w_b``, its world frame: the first frame's pose) over
        every frame it placed, timed by ``timestamps`` [N] (s, the sequence's); None if it
        placed none."""
        if not self.poses:
            return None
        fs = sorted(self.poses)
        return Trajectory(np.asarray(timestamps, np.float64)[fs], np.stack([self.poses[f] for f in fs]))

    def relative(self, a: int, b: int) -> np.ndarray:
        """``T_a^-1 T_b`` [4,4]: the rig's motion from frame ``a`` to frame ``b``."""
        return invert(self.poses[a]) @ self.poses[b]

    def span(self, a: int, b: int) -> list:
        """The frames it tracked after ``a`` up to ``b`` (``frames`` ascend: a bisection, not a
        scan of the whole run)."""
        return self.frames[bisect.bisect_right(self.frames, a) : bisect.bisect_right(self.frames, b)]

    def span_tracked(self, a: int, b: int) -> bool:
        """Whether keypoints placed every frame after ``a`` up to ``b`` (tracked frames only)."""
        fs = self.span(a, b)
        return a in self.poses and bool(fs) and all(self.tracked[f] and f in self.step_cov for f in fs)

    def relative_covariance(self, a: int, b: int) -> np.ndarray:
        """[6,6] covariance of :meth:`relative` ``(a, b)`` (right perturbation at ``b``): the
        steps' covariances moved to ``b`` by the adjoint of the motion after them and summed
        (steps taken as independent)."""
        fs = self.span(a, b)
        cov = np.zeros((6, 6))
        for f in fs:
            A = adjoint(invert(self.relative(f, b)))
            cov += A @ self.step_cov[f] @ A.T
        return cov
