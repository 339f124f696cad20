"""Multi-camera bundle adjustment: rig poses and per-pixel inverse depths (paper eq. 6-10).

Each iteration runs :func:`mcgs_warp.kernels.ba.mcba_linearize_kernel` over all
(edge, pixel) pairs, which reduces the weighted, Huber-robust Gauss-Newton system

    [ B   E ] [dxi]   [v]
    [ E^T C ] [dd ] = [w]          (eq. 9)

into per-edge pose blocks, per-pixel couplings and the diagonal depth block C.
Python eliminates the depths with the Schur complement (eq. 10, ``C^-1 = 1/C``):
``(B - E C^-1 E^T) dxi = v - E C^-1 w``, solves the small dense pose system with
SciPy, back-substitutes ``dd = C^-1 (w - E^T dxi)``, and accepts the step only if
the robust cost falls (Levenberg-Marquardt: otherwise the damping grows). The
first keyframe of the window is held fixed (gauge).

An optional depth prior (sensor or JDSA-scaled monocular depth) adds
``prior_weight * (1/prior - d)^2`` per pixel, in inverse depth.

A correspondence whose target or weight is NaN or infinite counts with weight 0 (the
kernels test it, so the cost and the linearization agree): it drops out, and the
rest of the problem is still solved.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import warp as wp

from ..buffer import KeyframeBuffer
from ..geometry import matrix_to_transform7, se3_exp
from ..kernels.camera import FAR


@dataclass
class MCBAConfig:
    """Solver settings. The defaults are the tuned values the system runs with
    (``mcgs_warp.system.config.TrackingConfig`` takes its defaults from here)."""

    iterations: int = 6  # Levenberg-Marquardt iterations per solve
    huber_delta: float = 0.1  # px on the reduced grid (0.8 px at stride 8): rejects flow bleeding across depth edges
    lm_lambda: float = 1e-4  # initial Levenberg-Marquardt damping (relative to the diagonal)
    prior_weight: float = 0.0  # weight of the inverse-depth prior, px^2 m^2 (0: no prior)
    min_disp: float = 1.0 / FAR  # 1/m: depths beyond the far plane are clamped to it


@dataclass
class MCBAStats:
    cost: list = field(default_factory=list)  # robust cost after each accepted step (first: initial)
    keyframes: list = field(default_factory=list)
    depth_info: np.ndarray | None = None  # [n,C,h,w] Gauss-Newton information of each inverse depth from the correspondences alone (last linearization)
    accepted: int = 0
    rejected: int = 0
    seconds_kernel: float = 0.0
    seconds_reduce: float = 0.0
    seconds_solve: float = 0.0


class MCBA:
    """Solves MCBA over a window of the keyframe buffer (poses and depths in place)."""

    def __init__(self, buffer: KeyframeBuffer, config: MCBAConfig | None = None):
        self.buf = buffer
        self.cfg = config or MCBAConfig()

    # ----------------------------------------------------------------------------------
    def _arrays(self, edges, targets, weights):
        dev = self.buf.device
        e4 = np.ascontiguousarray(edges[:, :4], dtype=np.int32)
        return (
            wp.array(e4, dtype=wp.vec4i, device=dev),
            wp.array(np.ascontiguousarray(targets, dtype=np.float32), dtype=wp.vec2, device=dev),
            wp.array(np.ascontiguousarray(weights, dtype=np.float32), dtype=float, device=dev),
        )

    def prior_target(self, keyframes) -> tuple[np.ndarray, np.ndarray]:
        """Inverse-depth prior [k,C,h,w] of ``keyframes`` (JDSA-scaled) and its per-pixel
        weight (the prior's confidence, 0 where it has no depth)."""
        from .jdsa import scale_field

        buf = self.buf
        prior = buf.depth_prior[keyframes].astype(np.float64)
        field_ = np.array([[scale_field(buf.scales[k, c], buf.h, buf.w) for c in range(len(buf.rig))] for k in keyframes])
        scaled = prior * field_
        mask = scaled > 0
        return np.where(mask, 1.0 / np.where(mask, scaled, 1.0), 0.0), mask * buf.prior_conf[keyframes]

    def cost(self, edge_arrays, n_edges: int, disp=None, poses=None, prior=None) -> float:
        """Robust reprojection cost plus the prior cost at the given (or current) state."""
        buf, dev = self.buf, self.buf.device
        e_arr, t_arr, w_arr = edge_arrays
        disp = buf.disp if disp is None else disp
        poses = buf.poses if poses is None else poses
        cost = wp.zeros(n_edges, dtype=float, device=dev)
        from ..kernels.ba import mcba_cost_kernel

        wp.launch(
            mcba_cost_kernel,
            dim=(n_edges, buf.h, buf.w),
            inputs=[buf.rays, disp, poses, buf.T_b_c, buf.cameras, e_arr, t_arr, w_arr, self.cfg.huber_delta],
            outputs=[cost],
            device=dev,
        )
        total = float(cost.numpy().astype(np.float64).sum())
        if prior is not None:
            kfs, target, mask = prior
            d = disp.numpy()[kfs].astype(np.float64)
            total += 0.5 * self.cfg.prior_weight * float(np.sum(mask * (target - d) ** 2))
        return total

    # ----------------------------------------------------------------------------------
    def solve(self, edges: np.ndarray, targets: np.ndarray, weights: np.ndarray, keyframes=None, fixed=None) -> MCBAStats:
        """Run LM iterations over ``edges`` [E,>=4] with correspondences ``targets``
        [E,h,w,2] (reduced-grid pixels) and ``weights`` [E,h,w].

        ``keyframes``: the window (default: every keyframe an edge touches); ``fixed``:
        keyframes whose pose is held (default: the first of the window)."""
        import time

        from ..kernels.ba import mat66, mcba_linearize_kernel
        from ..kernels.se3 import vec6

        buf, cfg, dev = self.buf, self.cfg, self.buf.device
        edges = np.asarray(edges)
        if keyframes is None:
            keyframes = np.unique(np.concatenate([edges[:, 0], edges[:, 2]]))
        keyframes = [int(k) for k in keyframes]
        fixed = {keyframes[0]} if fixed is None else {int(k) for k in fixed}
        slot = {k: s for s, k in enumerate(keyframes)}
        n, C, h, w = len(keyframes), len(buf.rig), buf.h, buf.w
        E = len(edges)
        stats = MCBAStats()
        if E == 0:
            return stats
        arrays = self._arrays(edges, targets, weights)
        prior = None
        if cfg.prior_weight > 0:
            target, mask = self.prior_target(keyframes)
            prior = (keyframes, target, mask)
        lam = cfg.lm_lambda
        current = self.cost(arrays, E, prior=prior)
        stats.cost.append(current)
        free = [s for s, k in enumerate(keyframes) if k not in fixed]
        free_idx = np.concatenate([np.arange(6 * s, 6 * s + 6) for s in free]) if free else np.zeros(0, int)

        for _ in range(cfg.iterations):
            t0 = time.perf_counter()
            H = wp.zeros((E, 3), dtype=mat66, device=dev)
            g = wp.zeros((E, 2), dtype=vec6, device=dev)
            Epix = wp.zeros((E, h, w, 2), dtype=vec6, device=dev)
            Cd = wp.zeros((buf.capacity, C, h, w), dtype=float, device=dev)
            wd = wp.zeros((buf.capacity, C, h, w), dtype=float, device=dev)
            cost = wp.zeros(E, dtype=float, device=dev)
            wp.launch(
                mcba_linearize_kernel,
                dim=(E, h, w),
                inputs=[buf.rays, buf.disp, buf.poses, buf.T_b_c, buf.cameras, *arrays, cfg.huber_delta],
                outputs=[H, g, Epix, Cd, wd, cost],
                device=dev,
            )
            Hn = H.numpy().astype(np.float64)
            gn = g.numpy().astype(np.float64)
            En = Epix.numpy().astype(np.float64).reshape(E, h * w, 2, 6)
            Cn = Cd.numpy()[keyframes].astype(np.float64).reshape(n, C, h * w)
            stats.keyframes, stats.depth_info = keyframes, Cn.reshape(n, C, h, w).copy()
            wn = wd.numpy()[keyframes].astype(np.float64).reshape(n, C, h * w)
            t1 = time.perf_counter()
            stats.seconds_kernel += t1 - t0

            disp_now = buf.disp.numpy()[keyframes].astype(np.float64).reshape(n, C, h * w)
            if prior is not None:
                pw = cfg.prior_weight * prior[2].reshape(n, C, h * w)
                Cn = Cn + pw
                wn = wn + pw * (prior[1].reshape(n, C, h * w) - disp_now)

            # Pose blocks.
            B = np.zeros((6 * n, 6 * n))
            v = np.zeros(6 * n)
            G = np.zeros((n, C, h * w, 6 * n))  # pose-depth coupling per depth variable
            for e, (i, ci, j) in enumerate(edges[:, :3]):
                if i == j:
                    continue
                si, sj = slot[i], slot[j]
                a, b = slice(6 * si, 6 * si + 6), slice(6 * sj, 6 * sj + 6)
                B[a, a] += Hn[e, 0]
                B[a, b] += Hn[e, 1]
                B[b, a] += Hn[e, 1].T
                B[b, b] += Hn[e, 2]
                v[a] += gn[e, 0]
                v[b] += gn[e, 1]
                G[si, ci, :, a] += En[e, :, 0]
                G[si, ci, :, b] += En[e, :, 1]

            # Schur complement with damped depth block.
            Cdamp = Cn * (1.0 + lam) + 1e-9
            Q = np.where(Cn > 0, 1.0 / Cdamp, 0.0)
            Gf = G.reshape(n * C, h * w, 6 * n)
            Qf = Q.reshape(n * C, h * w)
            wf = wn.reshape(n * C, h * w)
            S = B - np.einsum("npa,np,npb->ab", Gf, Qf, Gf, optimize=True)
            rhs = v - np.einsum("npa,np->a", Gf, Qf * wf, optimize=True)
            t2 = time.perf_counter()
            stats.seconds_reduce += t2 - t1

            while True:
                dxi = np.zeros(6 * n)
                if len(free_idx):
                    Sf = S[np.ix_(free_idx, free_idx)]
                    Sf = Sf + lam * np.diag(np.diag(Sf)) + 1e-9 * np.eye(len(free_idx))
                    try:
                        dxi[free_idx] = scipy.linalg.solve(Sf, rhs[free_idx], assume_a="sym")
                    except (np.linalg.LinAlgError, ValueError):
                        dxi[:] = 0.0
                Cdamp = Cn * (1.0 + lam) + 1e-9
                Q = np.where(Cn > 0, 1.0 / Cdamp, 0.0)
                dd = Q * (wn - np.einsum("ncpa,a->ncp", G, dxi))
                if not (np.all(np.isfinite(dxi)) and np.all(np.isfinite(dd))):
                    lam *= 10.0
                    stats.rejected += 1
                    if lam > 1e8:
                        break
                    continue
                # Candidate state.
                T_old = buf.get_poses()
                T_new = T_old.copy()
                for s_, k in enumerate(keyframes):
                    T_new[k] = T_old[k] @ se3_exp(dxi[6 * s_ : 6 * s_ + 6])
                disp_all = buf.disp.numpy()
                cand = disp_all.copy()
                cand[keyframes] = np.maximum(disp_now + dd, cfg.min_disp).reshape(n, C, h, w).astype(np.float32)
                cand[keyframes] = np.where(disp_all[keyframes] > 0, cand[keyframes], 0.0)
                disp_c = wp.array(cand, dtype=float, device=dev)
                poses_c = wp.array(matrix_to_transform7(T_new).astype(np.float32), dtype=wp.transform, device=dev)
                poses_full = wp.clone(buf.poses)
                wp.copy(poses_full, poses_c, count=len(T_new))
                new_cost = self.cost(arrays, E, disp=disp_c, poses=poses_full, prior=prior)
                if new_cost <= current:
                    buf.disp.assign(disp_c)
                    buf.poses.assign(poses_full)
                    current = new_cost
                    stats.cost.append(current)
                    stats.accepted += 1
                    lam = max(lam / 3.0, 1e-9)
                    break
                stats.rejected += 1
                lam *= 4.0
                if lam > 1e8:
                    break
            stats.seconds_solve += time.perf_counter() - t2
            if lam > 1e8:
                break
        return stats
