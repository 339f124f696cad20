"""The SLAM pipeline's wiring (paper Fig. 3): what the system is made of and the order in
which it runs, as DROID-SLAM's droid.py wires its parts.

Three stages with their own inputs and outputs share the keyframe buffer: the tracker
(:mod:`.tracker`: per frame the keypoint odometry and the keyframe test; per keyframe its
start, depth prior, MCBA (+ JDSA) over the sliding window and the health of the solve), which
alone writes poses and depths and returns per keyframe one
:class:`~mcgs_warp.mapping.follow.KeyframeUpdate` (what moved, then the keyframes to register
with their depth targets: the bootstrap rule, without exact depth keyframe 0 is mapped only
after keyframe 1's MCBA, and the lost filter are the tracker's); the mapper
(:class:`~mcgs_warp.mapping.mapper.Mapper`), which applies it
(:meth:`~mcgs_warp.mapping.mapper.Mapper.apply`) and runs mapping iterations over the
tracker's window, as ORB-SLAM3's tracking only inserts keyframes into its local mapper's
queue; after the last frame the offline stage (:meth:`SLAM.refine`: the global-BA backend's
MCBA with long and loop edges (:mod:`.backend`), photo-consistent depth targets
(:mod:`.offline`), joint refinement of map, poses and exposures). The online state is
checkpointed after every keyframe (:mod:`.checkpoint`). Deterministic for a seed.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..buffer import KeyframeBuffer
from ..data.sequence import Sequence
from ..data.trajectory import Trajectory
from ..mapping.gaussian_map import GaussianMap
from ..mapping.mapper import Mapper
from ..mapping.refine import joint_refinement
from .backend import Backend
from .checkpoint import load_checkpoint, save_checkpoint
from .config import RunConfig
from .memory import release_freed_memory
from .offline import photo_consistent_targets
from .tracker import Tracker


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


def refinement_steps(rc, keyframes: int) -> int:
    """Joint refinement's steps for ``keyframes`` registered keyframes: ``rc.iterations``, at
    most ``rc.steps_per_keyframe`` per keyframe (0: no limit)."""
    return min(rc.iterations, rc.steps_per_keyframe * keyframes) if rc.steps_per_keyframe > 0 else rc.iterations


class SLAM:
    """The system: its stages (:attr:`tracker`, :attr:`mapper`, :attr:`backend`), the loop over
    the frames (:meth:`run`) and the offline stage (:meth:`refine`)."""

    def __init__(self, sequence: Sequence, config: RunConfig, device=None, progress: Progress | None = None):
        self.seq = sequence
        self.cfg = config
        self.progress = progress or Progress(False)
        self.buf = KeyframeBuffer(sequence.rig, stride=config.tracking.stride, scale_grid=(config.tracking.jdsa_rows, config.tracking.jdsa_cols), device=device)  # grows with the keyframes
        self.tracker = self.make_tracker()
        # a region exact sensor depth measures is not sky
        self.mapper = Mapper(self.buf, GaussianMap(self.buf.device), config.mapping, seed=config.seed, sky_depth_veto=self.tracker.exact_depth)
        self.backend = Backend(self.tracker, config.refinement)
        self.seconds = {"tracking": 0.0, "mapping": 0.0, "refinement": 0.0}
        self.poses_before_global_ba = None  # keyframe T_w_b before the offline MCBA (benchmarks/scaling.py: drift)

    def make_tracker(self) -> Tracker:
        """The tracking stage (:class:`~mcgs_warp.system.posed_mapping.PosedMapping` holds the poses)."""
        return Tracker(self.seq, self.cfg, self.buf)

    def run(self, checkpoint=None, resume: bool = False, stop_after_keyframes: int | None = None) -> RunResult:
        """Process every frame, then refine. With ``checkpoint`` (a .npz path) the state is
        saved after each keyframe; ``resume`` continues from it. ``stop_after_keyframes``
        simulates an interruption (tests)."""
        n, tracker = len(self.seq), self.tracker
        kf_frames, last_images, start = [], None, 0
        if resume and checkpoint is not None and Path(checkpoint).is_file():
            start, kf_frames = load_checkpoint(self, checkpoint)
            last_images = self.seq[kf_frames[-1]].images if kf_frames else None
            self.progress("resumed", start, n, f"keyframes {len(kf_frames)}", force=True)
        for idx in range(start, n):
            frame, t0 = self.seq[idx], time.perf_counter()
            if not tracker.track(idx, frame, last_images):
                self.seconds["tracking"] += time.perf_counter() - t0
                self.progress("tracking", idx + 1, n, f"keyframes {len(kf_frames)}")
                continue
            update = tracker.add_keyframe(frame)  # its solve's moves, the keyframes to register (bootstrap, lost)
            kf_frames.append(idx)
            last_images, t1 = frame.images, time.perf_counter()
            self.mapper.apply(update, self.seq.rig)
            self.mapper.optimize_window(update.window, self.cfg.mapping.iterations_per_keyframe)
            release_freed_memory()  # this keyframe's temporaries: the heap would keep them (.memory)
            t2 = time.perf_counter()
            self.seconds["tracking"] += t1 - t0
            self.seconds["mapping"] += t2 - t1
            if checkpoint is not None:
                save_checkpoint(self, checkpoint, idx + 1, kf_frames)
            if stop_after_keyframes is not None and len(kf_frames) >= stop_after_keyframes:
                raise KeyboardInterrupt(f"stopped after {len(kf_frames)} keyframes")
            psnr = self.mapper.history[-1].psnr if self.mapper.history else float("nan")
            self.progress("tracking", idx + 1, n, f"keyframes {len(kf_frames)}  gaussians {len(self.mapper.map)}  psnr {psnr:.1f} dB")
        self.progress.done()
        tracker.close_lost_span()
        self.refine()
        traj = tracker.filler.trajectory()
        curve = [(i, r.loss, r.psnr) for i, r in enumerate(self.mapper.history)]
        return RunResult(traj, kf_frames, curve, dict(self.seconds))

    def refine(self) -> None:
        """The offline stage (paper Fig. 3, bottom): the backend's global MCBA over every
        keyframe with long and loop edges (:class:`~mcgs_warp.system.backend.Backend`; the map
        follows it), then photo-consistent depth targets from the solved poses
        (:func:`~mcgs_warp.system.offline.photo_consistent_targets`; estimated depth only),
        then joint refinement of map, poses and exposures."""
        rc, tracker = self.cfg.refinement, self.tracker
        t0 = time.perf_counter()
        self.poses_before_global_ba = self.buf.get_poses()
        if self.backend.active:
            self.progress("global BA", 0, 1, force=True)
            self.mapper.forget_loss_targets()  # global BA's arrays over every edge are the run's peak
            release_freed_memory()
            self.mapper.follow(self.backend.run(), self.seq.rig)
            release_freed_memory()
            self.seconds["global_ba"] = time.perf_counter() - t0
            self.progress("global BA", 1, 1, force=True)
            if rc.photo_depth_radius > 0 and not tracker.exact_depth:
                t1 = time.perf_counter()
                self.mapper.replace_targets(photo_consistent_targets(self.buf, tracker.stereo.pairs, range(len(self.buf)), rc.photo_depth_radius, rc.photo_depth_min_views, self.progress, rc.photo_depth_sources))
                release_freed_memory()
                self.seconds["photo_depth"] = time.perf_counter() - t1
        iterations = refinement_steps(rc, len(self.buf.targets))
        if iterations:
            def report(it, r):
                self.progress("refining", it + 1, iterations, f"psnr {r.psnr:.1f} dB")
                if (it + 1) % 30 == 0:
                    release_freed_memory()

            joint_refinement(self.mapper, iterations, poses=rc.poses, exposure=rc.exposure, progress=report)
            self.progress.done()
        self.seconds["refinement"] += time.perf_counter() - t0
