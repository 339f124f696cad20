"""Synthetic MCBA problems with exact correspondences, shared by the tests and the benchmark."""

from __future__ import annotations

import numpy as np

from mcgs_warp.ba.edges import build_edges, camera_overlap
from mcgs_warp.buffer import KeyframeBuffer
from mcgs_warp.frontend.depth import grid_depth
from mcgs_warp.frontend.flow import GroundTruthFlow
from mcgs_warp.geometry import se3_exp


class Problem:
    """Keyframes of a synthetic sequence in a buffer, at their true state, with GT flow."""

    def __init__(self, seq, frames, stride=8, cross_view=True, temporal=True, radius=2):
        rig = seq.rig
        self.seq = seq
        self.buf = KeyframeBuffer(rig, stride=stride, capacity=len(frames) + 2)
        depths = []
        for k in frames:
            f = seq[k]
            grid = grid_depth(f.depths, rig, stride, (self.buf.h, self.buf.w))
            disp = np.where(grid > 0, 1.0 / np.maximum(grid, 1e-6), 0.0)
            self.buf.add(k, f.timestamp, f.images, seq.groundtruth.poses[k], disp, depth_prior=grid)
            depths.append(f.depths)
        self.true_poses = self.buf.get_poses()
        self.true_disp = self.buf.disp.numpy()[: len(frames)].copy()
        overlap = camera_overlap(rig) if cross_view else None
        edges = build_edges(range(len(frames)), len(rig), overlap, radius=radius, cross_view=cross_view)
        if not temporal:
            edges = edges[edges[:, 0] == edges[:, 2]]
        self.edges = edges
        self.gt_flow = GroundTruthFlow(depths, self.true_poses)
        self.targets, self.weights = self.gt_flow.correspondences(self.buf, edges)

    def targets_for(self, edges):
        """Exact correspondences of other ``edges`` [E,>=4] among these keyframes."""
        return self.gt_flow.correspondences(self.buf, np.asarray(edges))

    def perturb(self, rng, trans=0.05, rot_deg=2.0, depth_noise=0.1, depth_scale=1.0, fixed=(0,)):
        T = self.true_poses.copy()
        for k in range(len(T)):
            if k in fixed:
                continue
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            step = np.concatenate([rng.normal(size=3), axis * np.radians(rot_deg)])
            step[:3] *= trans / np.linalg.norm(step[:3])
            T[k] = T[k] @ se3_exp(step)
        self.buf.set_poses(T)
        noise = np.exp(depth_noise * rng.normal(size=self.true_disp.shape))
        disp = np.where(self.true_disp > 0, self.true_disp * noise / depth_scale, 0.0)
        full = self.buf.disp.numpy()
        full[: len(disp)] = disp
        self.buf.disp.assign(full)

    def pose_errors(self):
        """Translation (m) and rotation (deg) errors per keyframe."""
        est = self.buf.get_poses()
        out = []
        for A, B in zip(est, self.true_poses):
            D = np.linalg.inv(B) @ A
            ang = np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
            out.append((np.linalg.norm(D[:3, 3]), ang))
        return np.array(out)

    def depth_rel_errors(self):
        """Relative depth errors of the pixels that have correspondences."""
        disp = self.buf.disp.numpy()[: len(self.true_disp)]
        used = np.zeros(self.true_disp.shape, bool)
        for e, (i, ci) in enumerate(self.edges[:, :2]):
            used[i, ci] |= self.weights[e] > 0
        return np.abs(self.true_disp[used] / disp[used] - 1.0)


def perturbed_pair(poses, slot: int, k: int, eps: float):
    """``poses`` [n,4,4] with pose ``slot`` right-multiplied by ``Exp(+eps e_k)`` and by
    ``Exp(-eps e_k)``: the two points of a central difference along twist coordinate ``k``."""
    from mcgs_warp.geometry import se3_exp

    d = np.zeros(6)
    d[k] = eps
    Pp, Pm = poses.copy(), poses.copy()
    Pp[slot] = Pp[slot] @ se3_exp(d)
    Pm[slot] = Pm[slot] @ se3_exp(-d)
    return Pp, Pm
