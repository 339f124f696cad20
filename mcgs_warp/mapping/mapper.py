"""Gaussian mapping over the keyframes of the buffer (paper §III-B, offline §III-C2).

Each iteration picks a keyframe, renders all of its rig views in one batched call,
applies the per-image affine exposure ``a * C + b``, and minimizes eq. 11:
colour (L1 + SSIM), depth L1 against the keyframe's depth, normal consistency
(normals of the rendered depth against those of the depth target, which stands in
for a monocular normal prior), and the scale regularizer; gradients come from our own adjoints, Adam updates the Gaussians
and, when enabled, the exposures and the keyframe rig poses (camera-pose
gradients mapped to the body frame with the adjoint of ``T_c_b``).

Densify and prune every ``densify_every`` iterations: clone small / split large
Gaussians whose mean view-space gradient is large, prune near-transparent and
oversized ones. New keyframes add Gaussians where the current map leaves the
image uncovered (rendered alpha below ``new_alpha``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..buffer import KeyframeBuffer
from ..geometry import adjoint, se3_exp
from ..kernels import Views, render, render_backward
from .gaussian_map import GaussianMap
from .losses import color_loss, depth_loss, normal_loss, psnr
from .optimizer import Adam

log = logging.getLogger("mcgs_warp.mapping")


@dataclass
class MappingConfig:
    lr_means: float = 2e-3  # m
    lr_log_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 0.05
    lr_colors: float = 5e-3
    lr_exposure: float = 1e-3
    lr_pose: float = 2e-4  # rad and m per step (Adam)
    lambda_ssim: float = 0.2
    lambda_depth: float = 0.05  # per m
    lambda_scale: float = 1.0  # per m (isotropy, eq. 11)
    lambda_normal: float = 0.05  # normal consistency with the depth target's normals (eq. 11)
    insert_stride: int = 4  # px between new Gaussians
    new_alpha: float = 0.5  # add Gaussians where rendered alpha is below this
    densify_every: int = 100
    densify_grad: float = 1e-5  # mean |dL/d mean2d| per view (loss per px) that triggers clone/split
    split_scale: float = 0.05  # m: larger Gaussians are split, smaller ones cloned
    prune_opacity: float = 0.01
    prune_scale: float = 2.0  # m
    max_gaussians: int = 400_000


@dataclass
class StepResult:
    loss: float
    psnr: float  # dB, mean over the keyframe's views
    keyframe: int


@dataclass
class DensifyReport:
    cloned: int = 0
    split: int = 0
    pruned: int = 0


class Mapper:
    def __init__(self, buffer: KeyframeBuffer, gmap: GaussianMap | None = None, config: MappingConfig | None = None, seed: int = 0):
        self.buf = buffer
        self.map = gmap or GaussianMap(buffer.device)
        self.cfg = config or MappingConfig()
        self.rng = np.random.default_rng(seed)
        self.cams = buffer.rig.warp_cameras()
        self._rays = None  # full-resolution unit-depth rays per camera (for normals), made on first use
        self.depths: dict[int, list] = {}  # keyframe -> full-res depth targets per camera
        C = len(buffer.rig)
        self.exposure = np.zeros((buffer.capacity, C, 2))  # (log a, b) per image: a * colour + b
        self.optimize_exposure = False
        self.optimize_poses = False
        self.fixed_poses: set[int] = {0}
        self.adam = self._new_adam()
        self._host_adam: dict = {}
        self.iteration = 0
        self._grad_accum = np.zeros(0)
        self._grad_count = np.zeros(0)
        self.history: list[StepResult] = []
        self.seconds = {"render": 0.0, "loss": 0.0, "backward": 0.0, "optimizer": 0.0}
        self.rejected_steps = 0

    def _new_adam(self) -> Adam:
        c = self.cfg
        return Adam({"means": c.lr_means, "log_scales": c.lr_log_scales, "quats": c.lr_quats, "opacity_logits": c.lr_opacity, "colors": c.lr_colors})

    # ----------------------------------------------------------------------------------
    def views(self, k: int) -> Views:
        T_w_c = self.buf.rig.camera_poses(self.buf.get_poses()[k])
        return Views.create(self.cams, T_w_c, self.buf.device)

    def add_keyframe(self, k: int, depths) -> int:
        """Register keyframe ``k`` of the buffer with full-resolution depth targets
        ``depths[c]`` [H,W] (m, 0 = none) and add Gaussians where the map is empty."""
        self.depths[k] = list(depths)
        images = self.buf.images[k]
        mask = None
        if len(self.map):
            out = render(self.map.gaussians, self.views(k))
            alpha = out.alpha.numpy()
            mask = [alpha[c, : s.height, : s.width] < self.cfg.new_alpha for c, s in enumerate(self.buf.rig.cameras)]
        before = len(self.map)
        added = self.map.insert_from_depth(self.buf.rig, self.buf.get_poses()[k], images, depths, anchor=k, stride=self.cfg.insert_stride, mask=mask)
        self._resize_state(np.concatenate([np.arange(before), -np.ones(added, int)]))
        return added

    def _resize_state(self, index: np.ndarray) -> None:
        n = len(index)
        for name, width in (("means", 3), ("log_scales", 3), ("quats", 4), ("opacity_logits", 1), ("colors", 3)):
            self.adam.remap(name, index, n, width)
        ok = index >= 0
        acc, cnt = np.zeros(n), np.zeros(n)
        if len(self._grad_accum):
            acc[ok], cnt[ok] = self._grad_accum[index[ok]], self._grad_count[index[ok]]
        self._grad_accum, self._grad_count = acc, cnt

    # ----------------------------------------------------------------------------------
    def step(self, k: int | None = None) -> StepResult:
        """One optimization step on keyframe ``k`` (default: a random registered keyframe)."""
        import time

        from ..kernels.mapping import isotropy_loss_kernel

        t0 = time.perf_counter()
        cfg, buf = self.cfg, self.buf
        if k is None:
            keys = sorted(self.depths)
            k = keys[self.rng.integers(len(keys))]
        g = self.map.gaussians
        views = self.views(k)
        out = render(g, views)
        color = out.color.numpy().astype(np.float64)
        depth = out.depth.numpy().astype(np.float64)
        C, H, W = color.shape[:3]
        t1 = time.perf_counter()
        gC = np.zeros((C, H, W, 3))
        gD = np.zeros((C, H, W))
        total, psnrs = 0.0, []
        exp_grad = np.zeros((C, 2))
        for c, spec in enumerate(buf.rig.cameras):
            h, w = spec.height, spec.width
            a, b = np.exp(self.exposure[k, c, 0]), self.exposure[k, c, 1]
            pred = a * color[c, :h, :w] + b
            target = buf.images[k][c]
            lc, gc = color_loss(pred, target, cfg.lambda_ssim)
            total += lc
            gC[c, :h, :w] = a * gc
            exp_grad[c] = [np.sum(gc * color[c, :h, :w]) * a, np.sum(gc)]
            psnrs.append(psnr(pred, target))
            d_t = self.depths[k][c]
            if d_t is not None and cfg.lambda_depth > 0:
                ld, gd = depth_loss(depth[c, :h, :w], d_t)
                total += cfg.lambda_depth * ld
                gD[c, :h, :w] = cfg.lambda_depth * gd
            if d_t is not None and cfg.lambda_normal > 0:
                ln, gn = normal_loss(depth[c, :h, :w], d_t, self.full_rays(c))
                total += cfg.lambda_normal * ln
                gD[c, :h, :w] += cfg.lambda_normal * gn
        t2 = time.perf_counter()
        params = {"means": g.means, "log_scales": g.log_scales, "quats": g.quats, "opacity_logits": g.opacity_logits, "colors": g.colors}
        train_map = any(self.adam.lrs.get(name, 0) > 0 for name in params)
        grads = None
        if train_map or (self.optimize_poses and k not in self.fixed_poses):
            grads = render_backward(g, views, out, grad_color=gC, grad_depth=gD)
        if grads is not None and cfg.lambda_scale > 0 and len(self.map):
            loss_s = wp.zeros(1, dtype=float, device=buf.device)
            wp.launch(isotropy_loss_kernel, dim=len(self.map), inputs=[g.log_scales, cfg.lambda_scale / len(self.map)], outputs=[loss_s, grads.log_scales], device=buf.device)
            total += float(loss_s.numpy()[0])
        t3 = time.perf_counter()
        if grads is not None and not self._finite(total, grads):
            # Numerical safety: a NaN/Inf loss or gradient never reaches the map or poses.
            self.rejected_steps += 1
            log.warning("mapping step %d on keyframe %d: non-finite loss or gradient, step rejected", self.iteration, k)
            self.iteration += 1
            result = StepResult(float("nan"), float("nan"), k)
            self.history.append(result)
            return result
        if train_map:
            self.adam.step(params, {name: getattr(grads, name) for name in params})
            # densification statistics: view-space gradient norm per Gaussian and view
            m2 = np.linalg.norm(grads.mean2d.numpy().reshape(C, -1, 2), axis=-1)
            vis = out.projection.visible.numpy().reshape(C, -1) > 0
            if len(self._grad_accum) != len(self.map):  # the map was replaced from outside
                self._grad_accum, self._grad_count = np.zeros(len(self.map)), np.zeros(len(self.map))
            self._grad_accum += m2.sum(0)
            self._grad_count += vis.sum(0)
        if self.optimize_exposure:
            self._host_adam_step(f"exposure{k}", self.exposure[k], exp_grad, cfg.lr_exposure)
        if self.optimize_poses and k not in self.fixed_poses:
            self._pose_step(k, grads.pose.numpy().astype(np.float64))
        self.iteration += 1
        if cfg.densify_every and self.iteration % cfg.densify_every == 0:
            self.densify_and_prune()
        t4 = time.perf_counter()
        for key, dt in (("render", t1 - t0), ("loss", t2 - t1), ("backward", t3 - t2), ("optimizer", t4 - t3)):
            self.seconds[key] += dt
        result = StepResult(total, float(np.mean(psnrs)), k)
        self.history.append(result)
        return result

    def full_rays(self, c: int) -> np.ndarray:
        """Unit-depth rays [H,W,3] of every pixel of camera ``c``."""
        if self._rays is None:
            from ..ba.graph import unproject_pixels

            self._rays = []
            for cam, spec in zip(self.cams, self.buf.rig.cameras):
                v, u = np.mgrid[0 : spec.height, 0 : spec.width]
                uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
                self._rays.append(unproject_pixels(cam, uv).reshape(spec.height, spec.width, 3))
        return self._rays[c]

    # ----------------------------------------------------------------------------------
    def state_arrays(self) -> dict:
        """Everything that determines the next steps, as arrays (for checkpoints)."""
        import json

        out = {f"map.{k}": v for k, v in self.map.to_numpy().items()}
        out.update({f"adam.{k}": v for k, v in self.adam.state_arrays().items()})
        out["exposure"] = self.exposure.copy()
        out["grad_accum"], out["grad_count"] = self._grad_accum.copy(), self._grad_count.copy()
        out["history"] = np.array([(r.loss, r.psnr, r.keyframe) for r in self.history], np.float64).reshape(-1, 3)
        host = {k: [m.tolist(), v.tolist(), t] for k, (m, v, t) in self._host_adam.items()}
        out["json"] = np.array(json.dumps({"iteration": self.iteration, "rng": self.rng.bit_generator.state, "host_adam": host, "rejected": self.rejected_steps, "registered": sorted(self.depths)}))
        return out

    def load_state_arrays(self, a: dict, depths: dict) -> None:
        import json

        self.map.set_numpy({k[4:]: a[k] for k in a if k.startswith("map.")})
        self.adam.load_state_arrays({k[5:]: a[k] for k in a if k.startswith("adam.")}, self.buf.device)
        self.exposure[:] = a["exposure"]
        self._grad_accum, self._grad_count = a["grad_accum"].copy(), a["grad_count"].copy()
        self.history = [StepResult(float(l_), float(p_), int(k_)) for l_, p_, k_ in a["history"]]
        meta = json.loads(str(a["json"]))
        self.iteration = meta["iteration"]
        self.rng.bit_generator.state = meta["rng"]
        self._host_adam = {k: (np.array(m), np.array(v), t) for k, (m, v, t) in meta["host_adam"].items()}
        self.rejected_steps = meta["rejected"]
        self.depths = {k: depths[k] for k in meta["registered"]}

    @staticmethod
    def _finite(total: float, grads) -> bool:
        if not np.isfinite(total):
            return False
        return all(np.isfinite(getattr(grads, n).numpy()).all() for n in ("means", "quats", "log_scales", "opacity_logits", "colors", "pose"))

    def _host_adam_step(self, key, value: np.ndarray, grad: np.ndarray, lr: float) -> np.ndarray:
        m, v, t = self._host_adam.get(key, (np.zeros_like(grad), np.zeros_like(grad), 0))
        t += 1
        m = 0.9 * m + 0.1 * grad
        v = 0.999 * v + 0.001 * grad * grad
        step = lr * (m / (1 - 0.9**t)) / (np.sqrt(v / (1 - 0.999**t)) + 1e-12)
        self._host_adam[key] = (m, v, t)
        value -= step
        return step

    def _pose_step(self, k: int, cam_grads: np.ndarray) -> None:
        """Map per-camera pose gradients to the rig body (xi_c = Ad(T_c_b) xi_b) and step."""
        g_body = np.zeros(6)
        for c, spec in enumerate(self.buf.rig.cameras):
            g_body += adjoint(np.linalg.inv(spec.T_b_c)).T @ cam_grads[c]
        xi = np.zeros(6)
        step = self._host_adam_step(f"pose{k}", xi, g_body, self.cfg.lr_pose)
        T = self.buf.get_poses()[k] @ se3_exp(-step)
        self.buf.set_poses(T[None], start=k)

    # ----------------------------------------------------------------------------------
    def densify_and_prune(self) -> DensifyReport:
        cfg = self.cfg
        d = self.map.to_numpy()
        n = len(d["means"])
        report = DensifyReport()
        if n == 0:
            return report
        mean_grad = self._grad_accum / np.maximum(self._grad_count, 1)
        scale = np.exp(d["log_scales"]).max(1)
        opacity = 1 / (1 + np.exp(-d["opacity_logits"]))
        keep = (opacity >= cfg.prune_opacity) & (scale <= cfg.prune_scale)
        report.pruned = int((~keep).sum())
        hot = keep & (mean_grad > cfg.densify_grad)
        room = max(cfg.max_gaussians - int(keep.sum()), 0)
        hot_idx = np.nonzero(hot)[0][:room]
        clone = hot_idx[scale[hot_idx] <= cfg.split_scale]
        split = hot_idx[scale[hot_idx] > cfg.split_scale]
        report.cloned, report.split = len(clone), len(split)
        index = [np.nonzero(keep & ~np.isin(np.arange(n), split))[0], clone]
        new = {key: [v[index[0]], v[clone]] for key, v in d.items()}
        if len(split):
            from ..kernels.reference import quat_to_rotation

            R = quat_to_rotation(d["quats"][split])
            s = np.exp(d["log_scales"][split])
            for _ in range(2):
                offset = np.einsum("nij,nj->ni", R, self.rng.normal(size=s.shape) * s)
                for key, v in d.items():
                    val = v[split]
                    if key == "means":
                        val = val + offset
                    elif key == "log_scales":
                        val = val - np.log(1.6)
                    new[key].append(val)
                index.append(-np.ones(len(split), int))
        self.map.set_numpy({key: np.concatenate(parts) for key, parts in new.items()})
        self._resize_state(np.concatenate(index))
        self._grad_accum[:] = 0
        self._grad_count[:] = 0
        return report

    def optimize(self, iterations: int, keyframes=None, progress=None) -> list[StepResult]:
        keys = sorted(self.depths) if keyframes is None else list(keyframes)
        results = []
        for it in range(iterations):
            results.append(self.step(keys[self.rng.integers(len(keys))]))
            if progress is not None:
                progress(it, results[-1])
        return results

    def evaluate(self, views) -> float:
        """Mean PSNR (dB) of renders against images: ``views`` is [(T_w_b, [image per camera])]."""
        values = []
        for T_w_b, imgs in views:
            out = render(self.map.gaussians, Views.create(self.cams, self.buf.rig.camera_poses(T_w_b), self.buf.device))
            col = out.color.numpy()
            for c, spec in enumerate(self.buf.rig.cameras):
                values.append(psnr(col[c, : spec.height, : spec.width], imgs[c]))
        return float(np.mean(values))

