"""The online SLAM loop and offline refinement (paper Fig. 3).

Per rig frame: keyframe test (mean DIS flow since the last keyframe); for a new
keyframe: initial pose by constant velocity, depth from the prior, MCBA (+ JDSA)
over the sliding window with temporal and cross-view edges (JDSA only for inexact,
monocular-style priors: rescaling exact sensor depth would free the metric scale), anchored Gaussians
follow the moved keyframes, new Gaussians where the map is empty, and mapping
iterations. Non-keyframe poses are interpolated between keyframes. After the last
frame: global MCBA over all keyframes, then joint refinement of map, poses and
exposures. Deterministic for a seed.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..ba.graph import build_edges, camera_overlap, sliding_window
from ..ba.jdsa import mcba_with_jdsa
from ..ba.mcba import MCBA, MCBAConfig
from ..buffer import KeyframeBuffer
from ..data.sequence import Sequence
from ..data.trajectory import Trajectory
from ..frontend.depth import default_prior, grid_depth
from ..frontend.flow import DISFlow
from ..frontend.keyframes import KeyframeSelector
from ..geometry import matrix_to_quat, quat_to_matrix
from ..mapping.gaussian_map import GaussianMap
from ..mapping.mapper import Mapper
from ..mapping.refine import joint_refinement
from .config import RunConfig


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
        self.flow = DISFlow()
        self.selector = KeyframeSelector(self.flow, threshold=tc.keyframe_flow_px)
        self.prior = default_prior(sequence)
        self.overlap = camera_overlap(sequence.rig, stride=tc.stride) if tc.cross_view else None
        self.mcba = MCBA(self.buf, MCBAConfig(iterations=tc.mcba_iterations, huber_delta=tc.huber_px, prior_weight=tc.prior_weight if self.prior.metric else 0.0))
        self.mapper = Mapper(self.buf, GaussianMap(self.buf.device), config.mapping, seed=config.seed)
        self._flows: dict = {}
        self.seconds = {"tracking": 0.0, "mapping": 0.0, "refinement": 0.0}

    # ----------------------------------------------------------------------------------
    def correspondences(self, edges: np.ndarray):
        """Flow targets and confidences per edge, computed once per edge and cached."""
        missing = [e for e in map(tuple, edges[:, :4].tolist()) if e not in self._flows]
        if missing:
            t, w = self.flow.correspondences(self.buf, np.array(missing, dtype=np.int32))
            for e, tt, ww in zip(missing, t, w):
                self._flows[e] = (tt, ww)
        keys = [tuple(e) for e in edges[:, :4].tolist()]
        return np.stack([self._flows[k][0] for k in keys]), np.stack([self._flows[k][1] for k in keys])

    def _solve(self, edges, keyframes):
        targets, weights = self.correspondences(edges)
        before = self.buf.get_poses()
        if self.cfg.tracking.jdsa and self.prior.metric and not self.prior.exact:
            mcba_with_jdsa(self.mcba, edges, targets, weights, keyframes=keyframes, rounds=self.cfg.tracking.jdsa_rounds)
        else:
            self.mcba.solve(edges, targets, weights, keyframes=keyframes)
        self.mapper.map.follow_keyframes(before, self.buf.get_poses())

    def add_keyframe(self, frame) -> int:
        buf, tc = self.buf, self.cfg.tracking
        poses = buf.get_poses()
        if len(buf) == 0:
            T_init = np.eye(4)  # the world frame is the first rig pose
        elif len(buf) == 1:
            T_init = poses[-1]
        else:
            T_init = poses[-1] @ np.linalg.inv(poses[-2]) @ poses[-1]  # constant velocity
        prior = grid_depth(self.prior(frame, self.seq.rig), self.seq.rig, tc.stride, (buf.h, buf.w))
        if (prior > 0).any():
            fill = float(np.median(prior[prior > 0]))
        else:
            fill = 3.0
        disp = np.where(prior > 0, 1.0 / np.maximum(prior, 1e-6), 1.0 / fill).astype(np.float32)
        k = buf.add(frame.index, frame.timestamp, frame.images, T_init, disp, depth_prior=prior if self.prior.metric else None)
        if len(buf) > 1:
            window = sliding_window(len(buf), tc.window)
            edges = build_edges(window, len(self.seq.rig), self.overlap, radius=tc.temporal_radius, cross_view=tc.cross_view)
            self._solve(edges, window)
        return k

    def mapping_depths(self, frame, k: int):
        """Depth targets for mapping: the sensor depth if metric, else MCBA depth upsampled."""
        import cv2

        if self.prior.metric:
            return list(frame.depths)
        d = self.buf.depth(k)
        return [cv2.resize(d[c, : s.height // self.buf.stride, : s.width // self.buf.stride], (s.width, s.height), interpolation=cv2.INTER_NEAREST) for c, s in enumerate(self.seq.rig.cameras)]

    # ----------------------------------------------------------------------------------
    def save_checkpoint(self, path, next_frame: int, kf_frames: list) -> None:
        """Write the whole online state atomically (``path``: a .npz file)."""
        import json

        from ..io import atomic_write

        buf, K = self.buf, len(self.buf)
        arrays = {f"mapper.{k}": v for k, v in self.mapper.state_arrays().items()}
        arrays.update(
            poses=buf.poses.numpy()[:K].copy(),
            disp=buf.disp.numpy()[:K].copy(),
            depth_prior=buf.depth_prior[:K].copy(),
            scales=buf.scales[:K].copy(),
            timestamps=np.array(buf.timestamps),
            frame_index=np.array(buf.frame_index, dtype=np.int64),
            kf_frames=np.array(kf_frames, dtype=np.int64),
            meta=np.array(json.dumps({"next_frame": next_frame, "config": self.cfg.to_dict(), "n_frames": len(self.seq), "seconds": self.seconds})),
        )
        with atomic_write(path, "wb") as f:
            np.savez(f, **arrays)

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
        if meta["config"] != self.cfg.to_dict() or meta["n_frames"] != len(self.seq):
            raise InputError(path, None, "checkpoint was written by a run with another configuration or sequence; start without --resume")
        buf = self.buf
        for k, fi in enumerate(a["frame_index"]):
            frame = self.seq[int(fi)]
            buf.add(int(fi), float(a["timestamps"][k]), frame.images, np.eye(4), a["disp"][k], depth_prior=a["depth_prior"][k])
        wp.copy(buf.poses, wp.array(a["poses"], dtype=wp.transform, device=buf.device), count=len(a["poses"]))
        buf.scales[: len(a["scales"])] = a["scales"]
        depths = {k: self.mapping_depths(self.seq[int(fi)], k) for k, fi in enumerate(a["frame_index"])}
        self.mapper.load_state_arrays({k[7:]: v for k, v in a.items() if k.startswith("mapper.")}, depths)
        self.seconds = meta["seconds"]
        return int(meta["next_frame"]), [int(v) for v in a["kf_frames"]]

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
            self.mapper.add_keyframe(k, self.mapping_depths(frame, k))
            window = sliding_window(len(self.buf), self.cfg.tracking.window)
            self.mapper.optimize(mcfg.iterations_per_keyframe, keyframes=window)
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
        if rc.global_ba_iterations and len(self.buf) > 1:
            self.progress("global BA", 0, 1, force=True)
            edges = build_edges(range(len(self.buf)), len(self.seq.rig), self.overlap, radius=self.cfg.tracking.temporal_radius, cross_view=self.cfg.tracking.cross_view)
            saved = self.mcba.cfg.iterations
            self.mcba.cfg.iterations = rc.global_ba_iterations
            self._solve(edges, list(range(len(self.buf))))
            self.mcba.cfg.iterations = saved
            self.progress("global BA", 1, 1, force=True)
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


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    return (np.sin((1 - u) * th) * q0 + np.sin(u * th) * q1) / np.sin(th)
