"""Gaussian mapping over the keyframes of the buffer (paper §III-B, offline §III-C2).

Each iteration picks a keyframe, renders all of its rig views in one batched call and
minimizes eq. 11 with the per-image affine exposure ``a * C + b`` applied: colour (L1 +
SSIM), depth L1 against the keyframe's depth, normal consistency (normals of the
rendered depth against those of the depth target, which stands in for a monocular
normal prior), and the scale regularizer. Gradients come from our own adjoints; one
Adam updates the Gaussians and, when enabled, the exposures and the keyframe rig poses
(camera-pose gradients mapped to the body frame with the adjoint of ``T_c_b``).

Roles: :class:`~.gaussian_map.GaussianMap` is the map (insert, densify, prune),
:class:`~.losses.MappingLoss` the image loss with its per-keyframe targets,
:class:`~.optimizer.Adam` the optimizer; the :class:`Mapper` orchestrates them. An
iteration stays on the device: its only host reads are the per-camera loss values and
a finiteness flag (to reject a step with NaN/Inf before anything changes).

Densify and prune every ``densify_every`` iterations: the map's gradient rules
(:meth:`GaussianMap.densify_and_prune`) plus the view rules of :meth:`Mapper.view_statistics`
(floaters in front of the keyframes' depth, an on-screen size budget). New keyframes add
Gaussians where the current map leaves the image uncovered (rendered alpha below
``new_alpha``) or renders behind the measured depth, also where no depth was measured
(faint, at the depth of the keyframe's measured neighbourhood: ``insert_fill``; such a Gaussian
is marked guessed until a view's depth target agrees with it, and :meth:`Mapper.depth_confidence`
renders the measured share per pixel), and, with ``sky``, never on the view's sky (:mod:`.sky`),
whose rendered alpha a cross-entropy term pushes to zero so the background shows there.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..buffer import KeyframeBuffer
from ..eval.metrics import psnr
from ..geometry import adjoint
from ..kernels import Views, blend, render, render_backward
from ..kernels import background as bg
from ..kernels.se3 import mat66
from .follow import KeyframeUpdate
from .gaussian_map import DensifyReport, GaussianMap, logit
from .losses import MappingLoss
from .optimizer import Adam, flat

__all__ = ["DensifyReport", "Mapper", "MappingConfig", "StepResult"]

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
    lr_background: float = 0.02  # per step: the background's spherical-harmonic coefficients (colour units)
    background: bool = True  # light the splats let through comes from a background at infinity (sky), colour by world direction (kernels/background.py); False: black
    background_cube: int = 32  # texels per face of the background's environment cube map on top of its harmonics (0: harmonics alone)
    lambda_ssim: float = 0.2
    lambda_depth: float = 1.0  # per m (0.2 before; seed 0 RGB only depth L1 0.119 -> 0.106 m, exact 0.045 -> 0.031 m and 30.16 -> 30.50 dB; held-out seed 1 RGB only 0.114 -> 0.100 m)
    lambda_scale: float = 1.0  # per m (isotropy, eq. 11)
    lambda_normal: float = 0.05  # normal consistency with the depth target's normals (eq. 11)
    sky: bool = False  # segment each keyframe view's sky (mapping/sky.py): no Gaussian is seeded there, it gets no depth target, and the rendered alpha there is penalized so the background shows the sky
    lambda_sky: float = 1.0  # weight of the sky term: binary cross-entropy of the rendered alpha against 0 on the sky, -log(1 - alpha), averaged over a camera's pixels (kernels/mapping.py)
    insert_stride: int = 4  # px between new Gaussians
    insert_fill: bool = True  # also seed Gaussians where no depth target is (uncovered, not sky), at the plane of the keyframe's measured neighbourhood (GaussianMap.insert_from_depth): the view is covered even where nothing measured depth
    fill_opacity: float = 0.1  # initial opacity of the Gaussians seeded at a guessed (filled) depth
    insert_max_depth: float = 100.0  # m: depth targets beyond this seed no Gaussian (the background stands for the far field)
    new_alpha: float = 0.5  # add Gaussians where rendered alpha is below this (or the render is floater_tolerance behind the measured depth)
    densify_every: int = 100
    densify_grad: float = 1e-5  # mean |dL/d mean2d| per view (loss per px) that triggers clone/split
    split_scale: float = 0.05  # m: larger Gaussians are split, smaller ones cloned
    prune_opacity: float = 0.01
    prune_scale: float = 2.0  # m
    prune_screen: float = 0.0  # prune Gaussians whose 3-sigma radius exceeds this share of the image width in any keyframe view (3DGS's screen-size rule, as a share so it survives resolution; 0: off)
    prune_floaters: bool = True  # prune Gaussians that keyframes see in front of their depth target (by more than floater_tolerance) more often than at it: floaters
    floater_tolerance: float = 0.2  # relative depth
    opacity_reset_every: int = 0  # iterations: clamp every opacity to 2 x prune_opacity (3DGS's opacity reset: what the views need recovers, floaters stay transparent and are pruned; 0: off)
    max_gaussians: int = 400_000
    target_cache: int = 32  # keyframes whose loss targets stay on the device (LRU)


@dataclass
class StepResult:
    loss: float
    psnr: float  # dB, mean over the keyframe's views
    keyframe: int


class Mapper:
    """Mapping over the keyframes of ``buffer``: ``apply`` takes the tracker's keyframe update
    (``follow`` its moves, ``add_keyframe`` registers a keyframe and its depth targets),
    ``step``/``optimize`` run Adam iterations. ``sky_depth_veto``: the run has exact sensor
    depth, and a region it measures is not sky (:func:`~.sky.sky_mask`).

    The keyframe state it trains against lives in the buffer: ``buffer.exposure`` (per
    image ``(log a, b)``, colour ``a * C + b``) and ``buffer.targets`` (the registered
    keyframes' depth targets)."""

    def __init__(self, buffer: KeyframeBuffer, gmap: GaussianMap | None = None, config: MappingConfig | None = None, seed: int = 0, sky_depth_veto: bool = False):
        self.buf = buffer
        self.map = gmap or GaussianMap(buffer.device)
        self.cfg = config or MappingConfig()
        self.rng = np.random.default_rng(seed)
        self.cams = buffer.rig.warp_cameras()
        dev = buffer.device
        self.optimize_exposure = False
        self.optimize_poses = False
        self.sky: dict[int, list] = {}  # keyframe -> per camera [H,W] bool sky mask (mapping/sky.py)
        self.sky_depth_veto = sky_depth_veto  # True with exact sensor depth: a region it measures is not sky
        self.placed: dict = {}  # keyframe -> grid depth [C,h,w] its Gaussians were last placed with (:meth:`follow`)
        self.fixed_poses: set[int] = {0}
        self.adam = self._new_adam()
        self.loss = MappingLoss(self.cams, dev, self.cfg.target_cache, rays=buffer.full_rays)
        self._background_image = None
        self.background = wp.zeros(bg.n_coeffs(self.cfg.background_cube), dtype=wp.vec3, device=dev)  # RGB per harmonic, then cube texels (kernels/background.py)
        # xi_c = Ad(T_c_b) xi_b: camera-pose gradients to the body, transposed adjoints per camera
        adj = np.stack([adjoint(np.linalg.inv(spec.T_b_c)).T for spec in buffer.rig.cameras]).astype(np.float32)
        self._adjoints_T = wp.array(adj, dtype=mat66, device=dev)
        self._pose_grad = wp.zeros(6, dtype=float, device=dev)  # dL/d xi_b
        self._pose_step = wp.zeros(6, dtype=float, device=dev)  # the increment Adam writes
        self._regularizers = wp.zeros(1, dtype=float, device=dev)  # the scale and sky terms of the step (summed on the device)
        self._nonfinite = wp.zeros(1, dtype=wp.int32, device=dev)
        self.iteration = 0
        self.history: list[StepResult] = []
        self.seconds = {"render": 0.0, "loss": 0.0, "backward": 0.0, "optimizer": 0.0}
        self.rejected_steps = 0

    def _new_adam(self) -> Adam:
        c = self.cfg
        return Adam({"means": c.lr_means, "log_scales": c.lr_log_scales, "quats": c.lr_quats, "opacity_logits": c.lr_opacity, "colors": c.lr_colors})

    # ----------------------------------------------------------------------------------
    def views(self, k: int) -> Views:
        """The rig views of keyframe ``k`` at its current pose (made on the device from the
        buffer's rig pose and extrinsics)."""
        from ..kernels.mapping import keyframe_viewmats_kernel

        dev = self.buf.device
        viewmats = wp.empty(len(self.cams), dtype=wp.mat44, device=dev)
        wp.launch(keyframe_viewmats_kernel, dim=len(self.cams), inputs=[self.buf.poses, self.buf.T_b_c, int(k)], outputs=[viewmats], device=dev)
        return Views(self.loss.cameras, viewmats, self.loss.W, self.loss.H)

    def colour(self, out, views: Views) -> wp.array:
        """The rendered colour [C,H,W] of ``out`` (a :func:`render` of ``views``, whose
        cameras are the rig's at the buffer's size) with the background behind the splats."""
        if not self.cfg.background:
            return out.color
        if self._background_image is None or self._background_image.shape != out.color.shape:
            self._background_image = wp.empty_like(out.color)  # B(d) per pixel of the last composite, for its backward pass
        return bg.composite(out.color, out.alpha, self.loss.rays, views.viewmats, views.cameras, self.background, background=self._background_image)

    def render(self, views: Views):
        """``(colour, render)``: :func:`render` of ``views`` and its colour with the background."""
        out = render(self.map.gaussians, views)
        return self.colour(out, views), out

    def depth_confidence(self, out, views: Views) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel of ``out`` (a :meth:`render` of ``views`` by this map), [C,H,W] each: the
        share of its blended weight that comes from measured Gaussians
        (:attr:`GaussianMap.measured`; 0 where nothing renders), and the spread of the blended
        Gaussians' depths around the median depth, ``sqrt(sum w (z - z_median)^2 / alpha) /
        z_median`` (inf where there is no median depth). A rendered depth was measured where the
        share is at least 0.5, and it stands for one surface where the spread is small; at a
        depth edge the blend mixes surfaces and the median may be either."""
        import dataclasses

        shape = out.alpha.shape
        if len(self.map) == 0:
            return np.zeros(shape, np.float32), np.full(shape, np.inf, np.float32)
        z = out.projection.depth.numpy()  # [C*N] each Gaussian's depth in each view
        m = np.tile(self.map.measured.astype(np.float32), views.n)
        colours = wp.array(np.stack([m, z, z * z], 1).astype(np.float32), dtype=wp.vec3, device=self.buf.device)
        per_view = dataclasses.replace(out.projection, n_gaussians=z.shape[0])  # colours by (view, Gaussian), not by Gaussian
        moments = blend(per_view, out.bins, colours, views).color.numpy().astype(np.float64)
        alpha, med = out.alpha.numpy().astype(np.float64), out.median_depth.numpy().astype(np.float64)
        a = np.maximum(alpha, 1e-4)
        share = np.where(alpha > 1e-4, np.clip(moments[..., 0] / a, 0.0, 1.0), 0.0)
        second = moments[..., 2] / a - 2 * med * moments[..., 1] / a + med * med
        spread = np.where(med > 0, np.sqrt(np.maximum(second, 0.0)) / np.maximum(med, 1e-9), np.inf)
        return share.astype(np.float32), spread.astype(np.float32)

    def add_keyframe(self, k: int, depths, placed=None) -> int:
        """Register keyframe ``k`` of the buffer with full-resolution depth targets
        ``depths[c]`` [H,W] (m, 0 = none) and add Gaussians where the map is empty;
        ``placed`` [C,h,w]: the grid depth they were placed with (:meth:`follow`)."""
        from .sky import sky_mask

        self.buf.targets[k] = list(depths)
        if placed is not None:
            self.placed[k] = np.asarray(placed)
        images = self.buf.keyframe_images(k)
        if self.cfg.sky:
            self.sky[k] = [sky_mask(images[c], depths[c] if self.sky_depth_veto else None, far=self.cfg.insert_max_depth) for c in range(len(self.cams))]
        free = [np.ones((s.height, s.width), bool) if not self.cfg.sky else ~self.sky[k][c] for c, s in enumerate(self.buf.rig.cameras)]
        mask = free
        if len(self.map):
            out = render(self.map.gaussians, self.views(k))
            alpha, rendered = out.alpha.numpy(), out.depth.numpy()
            # new Gaussians where the map is thin, and where it renders behind a measured depth
            # (something the map lacks stands in front: SplaTAM's rule; without it a surface
            # that guessed-depth Gaussians already cover is never seeded where it was measured)
            behind = [(d > 0) & (rendered[c, : s.height, : s.width] > (1 + self.cfg.floater_tolerance) * d) if d is not None else np.zeros((s.height, s.width), bool) for c, (s, d) in enumerate(zip(self.buf.rig.cameras, depths))]
            mask = [((alpha[c, : s.height, : s.width] < self.cfg.new_alpha) | behind[c]) & free[c] for c, s in enumerate(self.buf.rig.cameras)]
        before = len(self.map)
        added = self.map.insert_from_depth(self.buf.rig, self.buf.get_poses()[k], images, depths, anchor=k, stride=self.cfg.insert_stride, mask=mask, max_depth=self.cfg.insert_max_depth, fill=self.cfg.insert_fill, fill_opacity=self.cfg.fill_opacity)
        self._remap_optimizer(np.concatenate([np.arange(before), -np.ones(added, int)]))
        return added

    def apply(self, update: KeyframeUpdate, rig) -> None:
        """A new keyframe's update from tracking, in order: follow what its solve moved
        (:meth:`follow`), then register the keyframes it names (:meth:`add_keyframe`)."""
        self.follow(update.moved, rig)
        for r in update.register:
            self.add_keyframe(r.k, r.targets, placed=r.placed)

    def follow(self, updates, rig) -> None:
        """The map follows tracking's updates in order (:mod:`.follow`): a keyframe's anchored
        Gaussians move with its pose (:class:`~.follow.PosesMoved`); a mapped keyframe's follow
        the change of its grid depth from the one they were placed with along their rays (eq. 13
        per pixel, :func:`~.follow.depth_ratio`) and its depth targets become the new ones
        (:class:`~.follow.DepthMoved`)."""
        from .follow import PosesMoved, depth_ratio

        for u in updates:
            if isinstance(u, PosesMoved):
                self.map.follow_keyframes(u.before, u.after)
                continue
            old = self.placed[u.k]
            ratio = depth_ratio(old, u.depth)
            self.map.follow_depth(u.k, u.T_w_b, rig, self.buf.cameras, ratio)
            # what the Gaussians now stand for: the part of the change the filter or clip held back stays due
            self.placed[u.k] = np.where((old > 0) & (u.depth > 0), old * ratio, u.depth)
            self.buf.targets[u.k] = u.targets

    def replace_targets(self, targets: dict) -> None:
        """New full-resolution depth targets for mapped keyframes (keyframe -> per camera
        [H,W] m): new lists, so that the loss uploads them again."""
        self.buf.targets.update({k: list(v) for k, v in targets.items()})

    def forget_loss_targets(self) -> None:
        """Drop the cached loss targets (images, depths and SSIM moments on the device, up to
        ``losses.CACHE_BYTES``); they are made again when a keyframe is next optimized. For
        a stage that does not map (global BA), whose peak memory they would add to."""
        self.loss.forget()

    def _remap_optimizer(self, index: np.ndarray) -> None:
        """Carry the Gaussians' Adam moments to a new order (``index``: source or -1)."""
        for name, width in (("means", 3), ("log_scales", 3), ("quats", 4), ("opacity_logits", 1), ("colors", 3)):
            self.adam.remap(name, index, len(index), width)

    # ----------------------------------------------------------------------------------
    def step(self, k: int | None = None, densify: bool = True) -> StepResult:
        """One optimization step on keyframe ``k`` (default: a random registered keyframe);
        ``densify``: densify and prune when the iteration count says so (``densify_every``)."""
        from ..kernels.mapping import count_nonfinite_kernel, isotropy_loss_kernel

        t0 = time.perf_counter()
        cfg, buf, dev = self.cfg, self.buf, self.buf.device
        if k is None:
            keys = sorted(self.buf.targets)
            k = keys[self.rng.integers(len(keys))]
        g = self.map.gaussians
        views = self.views(k)
        colour, out = self.render(views)
        t1 = time.perf_counter()
        targets = self.loss.targets(k, buf.images[k], buf.targets[k], self.sky.get(k))  # the stored list: its identity keys the cache
        res = self.loss(colour, out.depth, targets, buf.exposure[k], cfg.lambda_ssim, cfg.lambda_depth, cfg.lambda_normal)
        t2 = time.perf_counter()
        params = {"means": g.means, "log_scales": g.log_scales, "quats": g.quats, "opacity_logits": g.opacity_logits, "colors": g.colors}
        train_map = any(self.adam.lrs.get(name, 0) > 0 for name in params)
        step_pose = self.optimize_poses and k not in self.fixed_poses
        grads = None
        self._nonfinite.zero_()
        self._regularizers.zero_()
        grad_background = None
        if train_map or step_pose:
            grad_alpha = None
            if cfg.background:
                grad_alpha, grad_background = bg.composite_backward(out.alpha, self.loss.rays, views.viewmats, views.cameras, self.background, res.grad_color, background=self._background_image)
            if targets.sky is not None and cfg.lambda_sky > 0:
                from ..kernels.mapping import sky_alpha_loss_kernel

                if grad_alpha is None:
                    grad_alpha = wp.zeros(out.alpha.shape, dtype=float, device=dev)
                wp.launch(sky_alpha_loss_kernel, dim=out.alpha.shape, inputs=[out.alpha, targets.sky, float(cfg.lambda_sky)], outputs=[self._regularizers, grad_alpha], device=dev)
            grads = render_backward(g, views, out, grad_color=res.grad_color, grad_depth=res.grad_depth, grad_alpha=grad_alpha)
            if cfg.lambda_scale > 0 and len(self.map):
                wp.launch(isotropy_loss_kernel, dim=len(self.map), inputs=[g.log_scales, cfg.lambda_scale / len(self.map)], outputs=[self._regularizers, grads.log_scales], device=dev)
            for values in [flat(getattr(grads, name)) for name in ("means", "quats", "log_scales", "opacity_logits", "colors", "pose")] + ([flat(grad_background)] if grad_background is not None else []):
                if values.shape[0]:
                    wp.launch(count_nonfinite_kernel, dim=values.shape[0], inputs=[values], outputs=[self._nonfinite], device=dev)
        total, psnrs = res.values()
        if grads is not None:
            total += float(self._regularizers.numpy()[0])
        t3 = time.perf_counter()
        if grads is not None and (not np.isfinite(total) or self._nonfinite.numpy()[0] > 0):
            # Numerical safety: a NaN/Inf loss or gradient never reaches the map or poses.
            self.rejected_steps += 1
            log.warning("mapping step %d on keyframe %d: non-finite loss or gradient, step rejected", self.iteration, k)
            self.iteration += 1
            result = StepResult(float("nan"), float("nan"), k)
            self.history.append(result)
            return result
        if train_map:
            self.adam.step(params, {name: getattr(grads, name) for name in params})
            self.map.accumulate_view_gradients(grads.mean2d, out.projection.visible, views.n)
            if grad_background is not None:
                self.adam.step_group("background", self.background, grad_background, cfg.lr_background)
        if self.optimize_exposure:
            self.adam.step_group(f"exposure{k}", buf.exposure[k], res.grad_exposure, cfg.lr_exposure)
        if step_pose:
            self._step_pose(k, grads.pose)
        self.iteration += 1
        if densify and cfg.densify_every and self.iteration % cfg.densify_every == 0:
            self.densify_and_prune()
        if cfg.opacity_reset_every and self.iteration % cfg.opacity_reset_every == 0:
            self.reset_opacity()
        t4 = time.perf_counter()
        for key, dt in (("render", t1 - t0), ("loss", t2 - t1), ("backward", t3 - t2), ("optimizer", t4 - t3)):
            self.seconds[key] += dt
        result = StepResult(total, float(np.mean(psnrs)), k)
        self.history.append(result)
        return result

    def _step_pose(self, k: int, camera_grads: wp.array) -> None:
        """Adam step of keyframe ``k``'s rig pose from per-camera pose gradients [C] vec6:
        the increment ``xi_b`` starts at 0 and ``T_w_b <- T_w_b @ Exp(xi_b)``."""
        from ..kernels.mapping import body_pose_gradient_kernel, retract_pose_kernel

        dev = self.buf.device
        wp.launch(body_pose_gradient_kernel, dim=1, inputs=[camera_grads, self._adjoints_T, len(self.cams)], outputs=[self._pose_grad], device=dev)
        self._pose_step.zero_()
        self.adam.step_group(f"pose{k}", self._pose_step, self._pose_grad, self.cfg.lr_pose)
        wp.launch(retract_pose_kernel, dim=1, inputs=[self.buf.poses, int(k), self._pose_step], device=dev)

    def full_rays(self, c: int) -> np.ndarray:
        """Unit-depth rays [H,W,3] (float64) of every pixel of camera ``c``."""
        spec = self.buf.rig.cameras[c]
        return self.loss.rays.numpy()[c, : spec.height, : spec.width].astype(np.float64)

    # ----------------------------------------------------------------------------------
    def state_arrays(self) -> dict:
        """Everything that determines the next steps, as arrays (for checkpoints)."""
        import json

        out = {f"map.{k}": v for k, v in self.map.to_numpy().items()}
        out.update({f"adam.{k}": v for k, v in self.adam.state_arrays().items()})
        out["grad_accum"], out["grad_count"] = self.map.statistics()
        out["background"] = self.background.numpy().copy()
        sky = sorted(self.sky)
        out["sky_keyframes"] = np.array(sky, np.int64)
        from .losses import pad_images

        padded = [pad_images([np.asarray(m, np.float32) for m in self.sky[k]], len(self.cams), self.loss.H, self.loss.W) > 0 for k in sky]
        out["sky"] = np.packbits(np.stack(padded)) if sky else np.zeros(0, np.uint8)  # [K,C,H,W] bits, padded to the largest camera
        out["history"] = np.array([(r.loss, r.psnr, r.keyframe) for r in self.history], np.float64).reshape(-1, 3)
        out["json"] = np.array(json.dumps({"iteration": self.iteration, "rng": self.rng.bit_generator.state, "rejected": self.rejected_steps, "registered": sorted(self.buf.targets)}))
        return out

    def load_state_arrays(self, a: dict, depths: dict) -> None:
        """Restore what :meth:`state_arrays` gave; ``depths``: keyframe -> depth targets (of
        which the registered keyframes' go to ``buffer.targets``)."""
        import json

        self.map.set_numpy({k[4:]: a[k] for k in a if k.startswith("map.")})
        self.map.set_statistics(a["grad_accum"], a["grad_count"])
        self.adam.load_state_arrays({k[5:]: a[k] for k in a if k.startswith("adam.")}, self.buf.device)
        self.background.assign(a["background"])
        sky = [int(k) for k in a["sky_keyframes"]]
        shape = (len(sky), len(self.cams), self.loss.H, self.loss.W)
        bits = np.unpackbits(a["sky"])[: int(np.prod(shape))].reshape(shape).astype(bool) if sky else None
        self.sky = {k: [bits[i, c, : s.height, : s.width].copy() for c, s in enumerate(self.buf.rig.cameras)] for i, k in enumerate(sky)}
        self.history = [StepResult(float(l_), float(p_), int(k_)) for l_, p_, k_ in a["history"]]
        meta = json.loads(str(a["json"]))
        self.iteration = meta["iteration"]
        self.rng.bit_generator.state = meta["rng"]
        self.rejected_steps = meta["rejected"]
        self.buf.targets.clear()
        self.buf.targets.update({k: depths[k] for k in meta["registered"]})
        self.loss.forget()

    # ----------------------------------------------------------------------------------
    def densify_and_prune(self) -> DensifyReport:
        """Adaptive density control of the map (:meth:`GaussianMap.densify_and_prune`
        with this mapper's settings, plus the view rules: screen size and floaters); the
        optimizer state follows."""
        cfg = self.cfg
        drop, floaters, oversized = None, None, None
        if (cfg.prune_screen > 0 or cfg.prune_floaters) and len(self.map) and self.buf.targets:
            radius, front, agree = self.view_statistics()
            oversized = radius > cfg.prune_screen * max(s.width for s in self.buf.rig.cameras) if cfg.prune_screen > 0 else np.zeros(len(self.map), bool)
            floaters = (front >= 2) & (front > agree) if cfg.prune_floaters else np.zeros(len(self.map), bool)
            drop = oversized | floaters
            self.map.measured |= agree >= 1  # a guessed Gaussian that a view's depth target now puts where it is was measured
        report, index = self.map.densify_and_prune(cfg.densify_grad, cfg.split_scale, cfg.prune_opacity, cfg.prune_scale, cfg.max_gaussians, self.rng, drop=drop)
        if drop is not None:
            report.floaters, report.oversized_on_screen = int(floaters.sum()), int(oversized.sum())
        self._remap_optimizer(index)
        return report

    def reset_opacity(self) -> None:
        """3DGS's opacity reset: every opacity clamped to at most 2 x ``prune_opacity``; the
        colour loss brings back what the views need, the rest is pruned at the next densify."""
        g = self.map.gaussians
        if len(self.map) == 0:
            return
        cap = float(logit(2 * self.cfg.prune_opacity))
        logits = g.opacity_logits.numpy()
        g.opacity_logits.assign(np.minimum(logits, cap).astype(np.float32))
        if "opacity_logits" in self.adam.state:  # moments of the old opacities would undo the reset
            m, v, t = self.adam.state["opacity_logits"]
            m.zero_()
            v.zero_()

    def view_statistics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per Gaussian over every registered keyframe view that sees it (projected centre
        inside the image): its largest 3-sigma screen radius (px), and how many views see it in
        front of their depth target (nearer than ``1 - floater_tolerance`` times it) and at it
        (within the tolerance). Views without a target at its pixel do not vote."""
        from ..kernels import project

        n, tol = len(self.map), self.cfg.floater_tolerance
        radius, front, agree = np.zeros(n), np.zeros(n, int), np.zeros(n, int)
        for k in sorted(self.buf.targets):
            proj = project(self.map.gaussians, self.views(k))
            uv, z, conic, vis = proj.mean2d.numpy(), proj.depth.numpy(), proj.conic.numpy(), proj.visible.numpy()
            for c, spec in enumerate(self.buf.rig.cameras):
                sl = slice(c * n, (c + 1) * n)
                u, v = np.floor(uv[sl, 0]).astype(np.int64), np.floor(uv[sl, 1]).astype(np.int64)
                seen = (vis[sl] > 0) & (u >= 0) & (u < spec.width) & (v >= 0) & (v < spec.height)
                a, b, cc = conic[sl, 0], conic[sl, 1], conic[sl, 2]
                # the largest eigenvalue of the 2D covariance is 1 / the smallest of the conic
                low = 0.5 * (a + cc) - np.sqrt(np.maximum(0.25 * (a - cc) ** 2 + b * b, 0.0))
                r = 3.0 * np.sqrt(1.0 / np.maximum(low, 1e-12))
                radius = np.where(seen, np.maximum(radius, r), radius)
                target = self.buf.targets[k][c]
                if target is None:
                    continue
                d = np.zeros(n)
                d[seen] = np.asarray(target)[v[seen], u[seen]]
                sky = self.sky.get(k)
                if sky is not None:
                    d[seen] = np.where(sky[c][v[seen], u[seen]], 0.0, d[seen])
                has = seen & (d > 0)
                front += has & (z[sl] < (1 - tol) * d)
                agree += has & (np.abs(z[sl] - d) <= tol * d)
        return radius, front, agree

    def optimize(self, iterations: int, keyframes=None, progress=None, densify: bool = True) -> list[StepResult]:
        """``iterations`` steps on random keyframes of ``keyframes`` (default: every registered
        one), densifying on schedule unless ``densify`` is false."""
        keys = sorted(self.buf.targets) if keyframes is None else list(keyframes)
        results = []
        for it in range(iterations):
            results.append(self.step(keys[self.rng.integers(len(keys))], densify=densify))
            if progress is not None:
                progress(it, results[-1])
        return results

    def optimize_window(self, window, iterations: int) -> list[StepResult]:
        """:meth:`optimize` over the registered keyframes of ``window`` (the tracker's sliding
        window, :attr:`KeyframeUpdate.window`); nothing while none of them is registered (before
        the first registration, or while tracking is lost over the whole window)."""
        keyframes = [k for k in window if k in self.buf.targets]
        return self.optimize(iterations, keyframes=keyframes) if keyframes else []

    def evaluate(self, views) -> float:
        """Mean PSNR (dB) of renders against images: ``views`` is [(T_w_b, [image per camera])]."""
        values = []
        for T_w_b, imgs in views:
            col = self.render(Views.create(self.cams, self.buf.rig.camera_poses(T_w_b), self.buf.device))[0].numpy()
            for c, spec in enumerate(self.buf.rig.cameras):
                values.append(psnr(col[c, : spec.height, : spec.width], imgs[c]))
        return float(np.mean(values))
