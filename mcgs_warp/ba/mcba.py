"""Multi-camera bundle adjustment: rig poses and per-pixel inverse depths (paper eq. 6-10).

Each iteration runs :func:`mcgs_warp.kernels.ba.mcba_linearize_kernel` over all
(edge, pixel) pairs, which reduces the weighted, Huber-robust Gauss-Newton system

    [ B   E ] [dxi]   [v]
    [ E^T C ] [dd ] = [w]          (eq. 9)

into per-edge pose blocks, per-pixel couplings and the diagonal depth block C.
The depths are eliminated with the Schur complement (eq. 10, ``C^-1 = 1/C``),
``(B - E C^-1 E^T) dxi = v - E C^-1 w``, sparsely and on the device: a depth of view
(i, ci) couples only to pose i and to the far poses of the edges leaving (i, ci), so
:func:`~mcgs_warp.kernels.ba.schur_pairs_kernel` reduces, for every pair of pose edges
leaving one view, four 6x6 blocks (all from one per-pixel sum: a pixel's coupling to pose i
is its coupling to pose j times the edge's adjoint, so only the latter is stored per pixel,
:func:`~mcgs_warp.kernels.ba.edge_adjoint`); ``schur_scatter_kernel`` and ``pose_system_kernel`` add
them and B's per-edge blocks into the 6n x 6n reduced camera system (float64), on the device. Work and memory grow with edges (and edge pairs) x grid
pixels, never with keyframes^2 beyond that small system. SciPy solves it; the
back-substitution ``dd = C^-1 (w - E^T dxi)``, the candidate state and its cost stay on
the device, and the step is accepted only if the robust cost falls
(Levenberg-Marquardt: otherwise the damping grows). All depth arrays are window-sized
(slot s = ``keyframes[s]``); the buffer is read once and written back after the solve.
The first keyframe of the window is held fixed (gauge).

An optional depth prior (sensor or JDSA-scaled monocular depth) adds
``0.5 * prior_weight * confidence * (1/prior - d)^2`` per pixel, in inverse depth.

A correspondence whose target or weight is NaN or infinite counts with weight 0 (the
kernels test it, so the cost and the linearization agree): it drops out, and the
rest of the problem is still solved.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..buffer import KeyframeBuffer
from ..kernels.camera import FAR
from ..kernels.launch import band_workers, run_row_bands
from .lm import Damping, damped_step, minimize
from .variance import ClassNoise, class_scales, dense_noise, disagreement_factor


@dataclass
class MCBAConfig:
    """Solver settings. The defaults are the tuned values the system runs with
    (``mcgs_warp.system.config.TrackingConfig`` takes its defaults from here)."""

    iterations: int = 4  # Levenberg-Marquardt iterations per solve
    huber_delta: float = 0.1  # px on the reduced grid (0.8 px at stride 8): rejects flow bleeding across depth edges
    lm_lambda: float = 1e-4  # initial Levenberg-Marquardt damping (relative to the diagonal)
    prior_weight: float = 0.0  # weight of the inverse-depth prior, px^2 m^2 (0: no prior)
    min_disp: float = 1.0 / FAR  # 1/m: depths beyond the far plane are clamped to it
    variance_components: bool = True  # weight the other residual classes against the dense one by their measured noise (:mod:`.variance`); False: their nominal weights


@dataclass
class MCBAStats:
    cost: list = field(default_factory=list)  # robust cost after each accepted step (first: initial)
    dense_cost: list = field(default_factory=list)  # ... its dense part (correspondences and depth prior), by which tracking health judges a solve
    keyframes: list = field(default_factory=list)
    depth_info: wp.array | None = None  # [n,C,h,w] (device) Gauss-Newton information of each inverse depth from the correspondences alone (last linearization)
    noise: object = None  # the dense class's ClassNoise at the solution (:mod:`.variance`), or None
    disagreement: float | None = None  # the dense class's variance factor its disagreement with the classes in absolute units gave in this solve
    scales: list = field(default_factory=list)  # weight of each other class (keypoints, factors) relative to the dense one in this solve
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
        self.noise = None  # the dense class's noise at the last solve's solution: the reference of the next solve's class weights
        self.disagreement: list = []  # the dense class's variance factor from each solve's disagreement with the classes in absolute units (:func:`~mcgs_warp.ba.variance.disagreement_factor`)

    def state_arrays(self) -> dict:
        """The measured noise the next solves weigh their classes by, for a checkpoint."""
        n = self.noise
        return {"mcba.noise": np.array([] if n is None else [n.n, n.redundancy, n.sigma2, n.kappa], np.float64), "mcba.disagreement": np.array(self.disagreement, np.float64)}

    def load_state_arrays(self, a: dict) -> None:
        n = a["mcba.noise"]
        self.noise = ClassNoise(int(n[0]), float(n[1]), float(n[2]), float(n[3])) if len(n) else None
        self.disagreement = [float(v) for v in a["mcba.disagreement"]]

    def dense_variance(self):
        """The dense class's variance factor for the next solve: what its residuals say
        (:attr:`noise`, correlation included) or, where larger, the median of what its
        disagreement with the classes in absolute units said so far; None before either."""
        own = None if self.noise is None else self.noise.effective
        if not self.disagreement:
            return own
        f = float(np.median(self.disagreement))
        return f if own is None else max(f, own)

    # ----------------------------------------------------------------------------------
    def _arrays(self, edges, targets, weights):
        return _edge_arrays(edges, targets, weights, self.buf.device)

    def prior_target(self, keyframes) -> tuple:
        """Inverse-depth prior [k,C,h,w] of ``keyframes`` (JDSA-scaled) and its per-pixel
        weight (the prior's confidence, 0 where it has no depth): device arrays
        (:func:`~mcgs_warp.ba.jdsa.scaled_prior`)."""
        from .jdsa import scaled_prior

        return scaled_prior(self.buf, keyframes)

    def cost(self, edge_arrays, n_edges: int, disp=None, poses=None, prior=None) -> float:
        """Robust reprojection cost plus the prior cost at the given (or current) state.

        ``edge_arrays``: :meth:`_arrays` of edges indexed like ``disp`` [K,C,h,w] and
        ``poses`` [K] (default: the buffer's); ``prior``: ``(keyframes, target, mask)`` with
        ``(target, mask)`` from :meth:`prior_target` of those keyframes."""
        from ..kernels.ba import window_copy_kernel

        buf, dev = self.buf, self.buf.device
        disp = buf.disp if disp is None else disp
        poses = buf.poses if poses is None else poses
        prior_dev = None
        if prior is not None:
            kfs, target, mask = prior
            kf = wp.array(np.asarray(kfs, dtype=np.int32), dtype=wp.int32, device=dev)
            window = wp.empty((len(kfs),) + tuple(disp.shape[1:]), dtype=float, device=dev)
            scratch = wp.empty(len(kfs), dtype=wp.transform, device=dev)
            wp.launch(window_copy_kernel, dim=window.shape, inputs=[kf, 1, disp, poses, window, scratch], device=dev)
            prior_dev = (window, target, mask)
        return _total_cost(buf, self.cfg, edge_arrays, n_edges, disp, poses, prior_dev)

    def reduced_system(self, edges: np.ndarray, targets: np.ndarray, weights: np.ndarray, keyframes=None, lam: float | None = None):
        """Linearize once at the current state and return the reduced camera system
        ``S`` [6n,6n] and ``rhs`` [6n] (float64, slots in the order of ``keyframes``;
        no gauge, no damping of ``S``; depth block damped by ``lam``, default the
        configured initial damping). For tests and diagnostics; :meth:`solve` uses the same path."""
        edges = np.asarray(edges)
        if len(edges) == 0:
            raise ValueError("reduced_system needs at least one edge")
        keyframes = self._window(edges, keyframes)
        prior = self.prior_target(keyframes) if self.cfg.prior_weight > 0 else None
        win = _Window(self.buf, self.cfg, keyframes, edges, targets, weights, prior)
        win.linearize()
        return win.reduce(self.cfg.lm_lambda if lam is None else lam)

    @staticmethod
    def _window(edges: np.ndarray, keyframes) -> list[int]:
        if keyframes is None:
            keyframes = np.unique(np.concatenate([edges[:, 0], edges[:, 2]]))
        return [int(k) for k in keyframes]

    # ----------------------------------------------------------------------------------
    def solve(self, edges: np.ndarray, targets: np.ndarray, weights: np.ndarray, keyframes=None, fixed=None, keypoints=None, factors=(), config: MCBAConfig | None = None) -> MCBAStats:
        """Run LM iterations over ``edges`` [E,>=4] with correspondences ``targets``
        [E,h,w,2] (reduced-grid pixels) and ``weights`` [E,h,w].

        ``keyframes``: the window (default: every keyframe an edge touches; every edge
        must stay inside it); ``fixed``: keyframes whose pose is held (default: the
        first of the window); ``keypoints``: a
        :class:`~mcgs_warp.ba.keypoint_factors.KeypointProblem` over the window's slots,
        whose tracks are solved with it (their inverse depths are updated in place);
        ``factors``: more pose factors over the window's slots with the same interface
        (``cost``, ``reduced_terms``, ``candidate``, ``accept``; e.g.
        :class:`~mcgs_warp.ba.depth_factors.DepthAlignmentFactors`); ``config``: this solve's
        settings instead of the solver's own (global BA's iterations and prior weight)."""
        from .keypoint_factors import KeypointFactors, window_poses

        cfg = config or self.cfg
        edges = np.asarray(edges)
        keyframes = self._window(edges, keyframes)
        fixed = {keyframes[0]} if fixed is None else {int(k) for k in fixed}
        stats = MCBAStats()
        if len(edges) == 0:
            return stats
        prior = self.prior_target(keyframes) if cfg.prior_weight > 0 else None
        win = _Window(self.buf, cfg, keyframes, edges, targets, weights, prior)
        kp = KeypointFactors(keypoints, self.buf.rig, self.buf.stride, cfg.huber_delta, cfg.min_disp) if keypoints is not None and len(keypoints) else None
        extra = ([kp] if kp else []) + [f for f in factors if len(f)]
        # each other class's weight against the dense one, from the noise measured at the last
        # solution (fixed through the solve, so that LM compares costs of one function)
        noises = [f.noise(window_poses(win.poses.numpy())) for f in extra]
        scales = class_scales(self.dense_variance(), noises) if cfg.variance_components else [1.0] * len(extra)
        stats.scales = scales
        dense = win.cost(win.disp, win.poses)
        current = dense + sum(s * f.cost(window_poses(win.poses.numpy())) for s, f in zip(scales, extra))
        stats.cost.append(current)
        stats.dense_cost.append(dense)
        free = [s for s, k in enumerate(keyframes) if k not in fixed]
        free_idx = np.concatenate([np.arange(6 * s, 6 * s + 6) for s in free]) if free else np.zeros(0, int)
        first, new_dense = True, None

        def linearize(lam):
            nonlocal first
            t0 = time.perf_counter()
            win.linearize()
            stats.keyframes = keyframes
            t1 = time.perf_counter()
            stats.seconds_kernel += t1 - t0
            S, rhs = win.reduce(lam)  # Schur complement with the damped depth block
            S_dense, rhs_dense = S, rhs
            S_abs, rhs_abs = np.zeros_like(S), np.zeros_like(rhs)  # the classes in absolute units
            for sc, f, nz in zip(scales, extra, noises):
                S_f, rhs_f = f.reduced_terms(window_poses(win.poses.numpy()), lam)
                if isinstance(nz, float):
                    S_abs, rhs_abs = S_abs + nz * S_f, rhs_abs + nz * rhs_f
                S, rhs = S + sc * S_f, rhs + sc * rhs_f
            if first and cfg.variance_components and len(free_idx) and S_abs.any():
                fac = disagreement_factor(S_dense[np.ix_(free_idx, free_idx)], rhs_dense[free_idx], S_abs[np.ix_(free_idx, free_idx)], rhs_abs[free_idx])
                if fac is not None:
                    self.disagreement.append(fac)
                    stats.disagreement = fac
            first = False
            stats.seconds_reduce += time.perf_counter() - t1
            return S, rhs

        def propose(lin, lam):
            nonlocal new_dense
            dxi = damped_step(*lin, free_idx, lam)
            if not (np.all(np.isfinite(dxi)) and win.candidate(dxi, lam)):
                return None
            new_dense = new_cost = win.cost(win.disp_c, win.poses_c)
            for sc, f in zip(scales, extra):
                f.candidate(dxi)
                new_cost += sc * f.cost(window_poses(win.poses_c.numpy()), getattr(f, "disp_c", None))
            return new_cost

        def accept(cost, new_cost):
            win.accept()
            for f in extra:
                f.accept()
            stats.cost.append(new_cost)
            stats.dense_cost.append(new_dense)

        t = time.perf_counter()
        res = minimize(current, linearize, propose, accept, cfg.iterations, Damping(cfg.lm_lambda))
        stats.accepted, stats.rejected = res.accepted, res.rejected
        stats.seconds_solve = time.perf_counter() - t - stats.seconds_kernel - stats.seconds_reduce
        if stats.accepted:
            win.store()
            if kp:
                keypoints.disp[:] = kp.disp
        if stats.keyframes:
            stats.depth_info = win.Cd  # the window's own array: no later solve writes it
        win.drop_linearization()  # before the noise's residual field: a global solve's peak memory
        if cfg.variance_components:
            stats.noise = win.noise(keyframes)
            if stats.noise is not None:
                self.noise = stats.noise
        return stats


class _Window:
    """Device state of one solve: the window's keyframes in slots ``0..n-1``.

    Every array is window-sized (``[n,C,h,w]`` depths, ``[n]`` poses) or edge-sized
    (``[E,h,w,...]`` couplings), never buffer-sized: edges are rewritten to slot indices
    once, the window's inverse depths and poses are gathered from the buffer once and
    written back by :meth:`store`. Inside the LM loop only the reduced camera system
    (``S`` [6n,6n], ``rhs`` [6n]), the 6n step and a few scalars cross between host and
    device."""

    def __init__(self, buf: KeyframeBuffer, cfg: MCBAConfig, keyframes: list, edges: np.ndarray, targets, weights, prior=None):
        from ..kernels.ba import mat66, mat66d, vec6d, window_copy_kernel
        from ..kernels.se3 import vec6

        self.buf, self.cfg, dev = buf, cfg, buf.device
        n, C, h, w = len(keyframes), len(buf.rig), buf.h, buf.w
        self.n, self.dev, self.shape = n, dev, (n, C, h, w)
        lut = np.full(max(int(edges[:, [0, 2]].max()), max(keyframes)) + 1, -1)
        lut[keyframes] = np.arange(n)
        ends = lut[edges[:, [0, 2]]]
        if np.any(ends < 0):
            raise ValueError(f"edges reach keyframes outside the window: {sorted(set(edges[:, [0, 2]][ends < 0].tolist()))}")
        sedges = np.ascontiguousarray(edges[:, :4], dtype=np.int32)
        sedges[:, 0], sedges[:, 2] = ends[:, 0], ends[:, 1]
        self.arrays = _edge_arrays(sedges, targets, weights, dev)
        E = self.E = len(sedges)

        self.kf = wp.array(np.asarray(keyframes, dtype=np.int32), dtype=wp.int32, device=dev)
        self.disp = wp.empty(self.shape, dtype=float, device=dev)
        self.poses = wp.empty(n, dtype=wp.transform, device=dev)
        wp.launch(window_copy_kernel, dim=self.shape, inputs=[self.kf, 1, buf.disp, buf.poses, self.disp, self.poses], device=dev)
        self.disp_c = wp.empty_like(self.disp)
        self.poses_c = wp.empty_like(self.poses)

        # Linearization (eq. 9), the depth terms with the prior, back-substitution.
        self.H = wp.empty((E, 3), dtype=mat66d, device=dev)
        self.g = wp.empty((E, 2), dtype=vec6d, device=dev)
        self.Epix = wp.empty((E, h, w), dtype=vec6, device=dev)  # pose j's couplings; pose i's via self.Ad
        self.Ad = wp.empty(E, dtype=mat66, device=dev)  # each edge's adjoint at the linearization (kernels.ba.edge_adjoint)
        self.edge_step = wp.empty(E, dtype=vec6, device=dev)
        self.Cd = wp.empty(self.shape, dtype=float, device=dev)
        self.wd = wp.empty(self.shape, dtype=float, device=dev)
        self.prior = None
        self.Ct, self.wt = self.Cd, self.wd  # depth block and gradient with the prior
        if prior is not None:
            self.prior = tuple(prior)  # device arrays (target, mask), from MCBA.prior_target
            self.Ct, self.wt = wp.empty_like(self.Cd), wp.empty_like(self.wd)
        self.edge_cost = wp.empty(E, dtype=float, device=dev)
        self.total = wp.empty(1, dtype=wp.float64, device=dev)
        # Per-edge sums of a launch banded over grid rows (CPU threads, kernels/launch.py):
        # each worker accumulates its own, summed in worker order afterwards (deterministic);
        # made at the first linearization, for the worker count of that moment.
        self.per_worker = None  # (H [W,E,3], g [W,E,2], cost [W,E])
        self.cost_scratch = None  # _total_cost's per-worker sums
        self.coupling = wp.empty(self.shape, dtype=float, device=dev)
        self.dxi = wp.empty(n, dtype=vec6, device=dev)
        self.nonfinite = wp.empty(1, dtype=wp.int32, device=dev)

        # Sparsity: pose edges (i != j), and the pairs (e1 <= e2) of pose edges leaving one
        # view (every pose edge pairs with itself, so P > 0 exactly when there are pose edges).
        si, ci, sj = sedges[:, 0], sedges[:, 1], sedges[:, 2]
        pe = np.flatnonzero(si != sj)
        key = si[pe].astype(np.int64) * C + ci[pe]
        order = pe[np.argsort(key, kind="stable")]
        groups = np.split(order, np.flatnonzero(np.diff(np.sort(key, kind="stable"))) + 1) if len(pe) else []
        pairs = np.array([(a, b) for grp in groups for k, a in enumerate(grp) for b in grp[k:]], dtype=np.int32).reshape(-1, 2)
        self.pe, self.P = pe, len(pairs)
        self.pose_edges = wp.array(pe.astype(np.int32), dtype=wp.int32, device=dev)
        self.pairs = wp.array(pairs, dtype=wp.vec2i, device=dev)
        self.blocks = wp.empty((self.P, 4), dtype=mat66d, device=dev)
        self.depth_rhs = wp.empty((E, 2), dtype=vec6d, device=dev)

        n6 = 6 * n
        self.S = wp.empty((n6, n6), dtype=wp.float64, device=dev)
        self.rhs = wp.empty(n6, dtype=wp.float64, device=dev)

    # ----------------------------------------------------------------------------------
    def linearize(self) -> None:
        """Run the MCBA kernel at the current window state; add the prior's depth terms."""
        from ..kernels.ba import edge_adjoint_kernel, mat66d, mcba_linearize_kernel, prior_terms_kernel, vec6d

        buf, cfg, dev, E = self.buf, self.cfg, self.dev, self.E
        workers = band_workers(dev, buf.h)
        banded = workers > 1
        if banded and (self.per_worker is None or self.per_worker[2].shape[0] < workers):
            self.per_worker = (wp.empty((workers, E, 3), dtype=mat66d, device=dev), wp.empty((workers, E, 2), dtype=vec6d, device=dev), wp.empty((workers, E), dtype=float, device=dev))
        sums = self.per_worker if banded else (self.H, self.g, self.edge_cost)
        for arr in (*sums, self.Epix, self.Cd, self.wd):
            arr.zero_()
        inputs = [buf.rays, self.disp, self.poses, buf.T_b_c, buf.cameras, *self.arrays, cfg.huber_delta]

        def band(worker, row0, rows):  # rows never share a depth (Cd, wd, Epix); per-edge sums go per worker
            H, g, cost = (a[worker] for a in sums) if banded else sums
            wp.launch(mcba_linearize_kernel, dim=(self.E, rows, buf.w), inputs=[*inputs, row0], outputs=[H, g, self.Epix, self.Cd, self.wd, cost], device=dev)

        run_row_bands(dev, buf.h, band)
        wp.launch(edge_adjoint_kernel, dim=E, inputs=[self.poses, self.arrays[0]], outputs=[self.Ad], device=dev)
        if banded:
            for total, parts in zip((self.H, self.g, self.edge_cost), sums):
                total.numpy()[...] = parts.numpy().sum(axis=0)  # CPU: numpy() is the array itself
        if self.prior is not None:
            wp.launch(
                prior_terms_kernel,
                dim=self.shape,
                inputs=[self.Cd, self.wd, self.disp, *self.prior, cfg.prior_weight],
                outputs=[self.Ct, self.wt],
                device=dev,
            )
        wp.synchronize_device(dev)

    def reduce(self, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """Reduced camera system ``S = B - E Q E^T`` [6n,6n] and ``rhs = v - E Q w`` [6n]
        (float64) of the last linearization, with the depth block damped by ``lam``."""
        from ..kernels.ba import pose_system_kernel, schur_pair_blocks_kernel, schur_pairs_kernel, schur_rhs_kernel, schur_scatter_kernel

        dev, h, e_arr = self.dev, self.buf.h, self.arrays[0]
        for arr in (self.blocks, self.depth_rhs, self.S, self.rhs):
            arr.zero_()
        if self.P:
            # banded over pairs and pose edges (each writes only its own blocks)
            run_row_bands(dev, self.P, lambda w, p0, n: wp.launch(schur_pairs_kernel, dim=(n, h), inputs=[self.Epix, self.Ct, e_arr, self.pairs, lam, p0], outputs=[self.blocks], device=dev))
            wp.launch(schur_pair_blocks_kernel, dim=self.P, inputs=[self.pairs, self.Ad], outputs=[self.blocks], device=dev)
            wp.launch(schur_scatter_kernel, dim=(self.P, 4, 6, 6), inputs=[self.blocks, self.pairs, e_arr], outputs=[self.S], device=dev)
            run_row_bands(
                dev,
                len(self.pe),
                lambda w, k0, n: wp.launch(schur_rhs_kernel, dim=(n, h), inputs=[self.Epix, self.Ad, self.Ct, self.wt, e_arr, self.pose_edges, lam, k0], outputs=[self.depth_rhs], device=dev),
            )
            wp.launch(pose_system_kernel, dim=(len(self.pe), 6, 6), inputs=[self.H, self.g, self.depth_rhs, e_arr, self.pose_edges], outputs=[self.S, self.rhs], device=dev)
        return self.S.numpy().copy(), self.rhs.numpy().copy()

    def candidate(self, dxi: np.ndarray, lam: float) -> bool:
        """Candidate state ``T @ Exp(dxi)``, ``max(d + dd, min_disp)`` into ``poses_c``,
        ``disp_c``; False where the back-substituted ``dd`` is not finite."""
        from ..kernels.ba import backsub_coupling_kernel, depth_candidate_kernel, edge_step_kernel, pose_candidate_kernel

        dev = self.dev
        self.dxi.assign(np.asarray(dxi, dtype=np.float32).reshape(self.n, 6))
        self.coupling.zero_()
        self.nonfinite.zero_()
        if len(self.pe):
            wp.launch(edge_step_kernel, dim=len(self.pe), inputs=[self.Ad, self.arrays[0], self.pose_edges, self.dxi], outputs=[self.edge_step], device=dev)
            wp.launch(
                backsub_coupling_kernel,
                dim=(len(self.pe), self.buf.h, self.buf.w),
                inputs=[self.Epix, self.arrays[0], self.pose_edges, self.edge_step],
                outputs=[self.coupling],
                device=dev,
            )
        wp.launch(
            depth_candidate_kernel,
            dim=self.shape,
            inputs=[self.disp, self.Ct, self.wt, self.coupling, lam, self.cfg.min_disp],
            outputs=[self.disp_c, self.nonfinite],
            device=dev,
        )
        wp.launch(pose_candidate_kernel, dim=self.n, inputs=[self.poses, self.dxi], outputs=[self.poses_c], device=dev)
        return int(self.nonfinite.numpy()[0]) == 0

    def cost(self, disp, poses) -> float:
        """Robust reprojection cost plus the prior cost of a window state (float64 sum)."""
        prior = None if self.prior is None else (disp, *self.prior)
        n = band_workers(self.dev, self.buf.h) * self.E
        if self.cost_scratch is None or self.cost_scratch.shape[0] < n:
            self.cost_scratch = wp.empty(n, dtype=float, device=self.dev)
        return _total_cost(self.buf, self.cfg, self.arrays, self.E, disp, poses, prior, self.cost_scratch, self.total)

    def noise(self, keyframes) -> "ClassNoise | None":
        """The dense class's noise at the current state (:func:`~mcgs_warp.ba.variance.dense_noise`):
        its whitened residual field, each view's depth shared with the prior by their
        information at the last linearization."""
        from ..kernels.ba import mcba_residual_kernel

        buf, dev = self.buf, self.dev
        res = wp.zeros((self.E, buf.h, buf.w), dtype=wp.vec2, device=dev)
        valid = wp.zeros((self.E, buf.h, buf.w), dtype=wp.int32, device=dev)
        inputs = [buf.rays, self.disp, self.poses, buf.T_b_c, buf.cameras, *self.arrays]
        run_row_bands(dev, buf.h, lambda w, row0, rows: wp.launch(mcba_residual_kernel, dim=(self.E, rows, buf.w), inputs=[*inputs, row0], outputs=[res, valid], device=dev))
        e = self.arrays[0].numpy()
        share = 1.0
        if self.prior is not None:
            Cd, Cp = self.Cd.numpy(), self.cfg.prior_weight * self.prior[1].numpy()
            seen = Cd > 0
            if seen.any():
                share = float(np.mean(Cd[seen] / (Cd[seen] + Cp[seen])))
        return dense_noise(res.numpy(), valid.numpy() > 0, e[:, 0] * len(buf.rig) + e[:, 1], share)

    def drop_linearization(self) -> None:
        """Free what only the LM iterations use (the per-pixel couplings, the per-edge and
        pair blocks, the candidate state): the largest arrays of a window, [E,h,w] vec6."""
        self.Epix = self.H = self.g = self.blocks = self.depth_rhs = self.per_worker = None
        self.coupling = self.disp_c = self.poses_c = self.S = self.rhs = None

    def accept(self) -> None:
        self.disp, self.disp_c = self.disp_c, self.disp
        self.poses, self.poses_c = self.poses_c, self.poses

    def store(self) -> None:
        """Write the window's state back into the keyframe buffer."""
        from ..kernels.ba import window_copy_kernel

        buf = self.buf
        wp.launch(window_copy_kernel, dim=self.shape, inputs=[self.kf, 0, buf.disp, buf.poses, self.disp, self.poses], device=self.dev)


def _edge_arrays(edges: np.ndarray, targets, weights, device):
    """Device arrays of edges [E] vec4i, correspondences [E,h,w] vec2 and weights [E,h,w]
    (on the CPU the float32 host arrays are shared, not copied: they are the largest inputs)."""
    device = wp.get_device(device)
    e4 = np.ascontiguousarray(edges[:, :4], dtype=np.int32)
    return (
        wp.array(e4, dtype=wp.vec4i, device=device),
        wp.array(np.ascontiguousarray(targets, dtype=np.float32), dtype=wp.vec2, device=device, copy=not device.is_cpu),
        wp.array(np.ascontiguousarray(weights, dtype=np.float32), dtype=float, device=device, copy=not device.is_cpu),
    )


def _total_cost(buf: KeyframeBuffer, cfg: MCBAConfig, edge_arrays, n_edges: int, disp, poses, prior=None, edge_cost=None, total=None) -> float:
    """Robust reprojection cost of ``edge_arrays`` at ``disp`` [K,C,h,w] and ``poses`` [K]
    (indexed as the edges are) plus, with ``prior = (disp_window, target, mask)``
    (device arrays [n,C,h,w]), the prior cost; summed in float64 on the device.
    ``edge_cost`` [>= workers * E] (per-worker sums of the row bands, see
    :func:`~mcgs_warp.kernels.launch.band_workers`) and ``total`` [1] are optional scratch arrays."""
    from ..kernels.ba import mcba_cost_kernel, prior_cost_kernel, sum_float64_kernel

    dev = buf.device
    workers = band_workers(dev, buf.h)
    if edge_cost is None or edge_cost.shape[0] < workers * n_edges:
        edge_cost = wp.empty(workers * n_edges, dtype=float, device=dev)
    total = wp.empty(1, dtype=wp.float64, device=dev) if total is None else total
    edge_cost.zero_()
    total.zero_()
    inputs = [buf.rays, disp, poses, buf.T_b_c, buf.cameras, *edge_arrays, cfg.huber_delta]
    run_row_bands(
        dev,
        buf.h,
        lambda w, row0, rows: wp.launch(mcba_cost_kernel, dim=(n_edges, rows, buf.w), inputs=[*inputs, row0], outputs=[edge_cost[w * n_edges : (w + 1) * n_edges]], device=dev),
    )
    wp.launch(sum_float64_kernel, dim=workers * n_edges, inputs=[edge_cost], outputs=[total], device=dev)
    if prior is not None:
        wp.launch(prior_cost_kernel, dim=prior[0].shape, inputs=[*prior, cfg.prior_weight], outputs=[total], device=dev)
    return float(total.numpy()[0])
