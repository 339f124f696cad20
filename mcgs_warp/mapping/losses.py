"""The image part of the mapping objective (paper eq. 11, with the 3DGS colour term), on
the device: values and gradients w.r.t. the rendered images and the exposures.

Per camera of a keyframe, with its affine exposure ``pred = a * colour + b``: colour
``(1 - l_ssim) * L1 + l_ssim * (1 - SSIM)``, depth ``l_depth * mean |D - d|`` where the
target depth ``d`` is known, and normal consistency ``l_normal * mean (1 - <n(D), n(d)>)``
(normals of back-projected depth; the target depth's normals stand in for the paper's
monocular normal prior); the loss is the sum over the keyframe's cameras. Definitions
and kernels: :mod:`mcgs_warp.kernels.losses`. The Gaussian-space scale regularizer
lives in :mod:`mcgs_warp.kernels.mapping`.

Targets (images, depths, their SSIM statistics and normals) are uploaded once per
keyframe and kept on the device in a small LRU cache; an entry is rebuilt when the
host lists or arrays it was made from are replaced (identity, not contents: change a
keyframe's targets by assigning new arrays, never in place).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..buffer import float_image
from ..kernels import Camera
from ..kernels.launch import run_row_bands
from ..kernels.losses import (
    blur_rows3_kernel,
    camera_sums_kernel,
    exposure_grad_kernel,
    image_grad_kernel,
    loss_summary_kernel,
    loss_terms_kernel,
    ssim_moments_rows_kernel,
    ssim_target_kernel,
    ssim_target_rows_kernel,
    ssim_window,
    target_normals_kernel,
    vec8d,
)

#: bytes of device memory the per-keyframe target cache may hold (:class:`MappingLoss`): 31 keyframes
#: of a 3-camera rig at 320x240 (it held 32 before it was counted in bytes), all of KITTI's stereo pair at
#: 640x194 up to 60 keyframes, 5 of a 6-camera surround rig at 640x360 (72 MB each: 32 of them were 2.3 GB)
CACHE_BYTES = 384 << 20

# Pixels of a row per thread in the two passes that also reduce: a whole row on the CPU
# (sums stay in registers), 16 on CUDA (enough threads, short per-camera sums).
CUDA_SEGMENT = 16


@dataclass
class KeyframeTargets:
    """One keyframe's loss targets on the device, padded to [C,H,W] (zero outside a camera)."""

    image: wp.array  # [C,H,W] vec3, RGB in [0, 1]
    depth: wp.array  # [C,H,W] float, m, 0 = none
    mu: wp.array  # [C,H,W] vec3, SSIM local mean of the image
    var: wp.array  # [C,H,W] vec3, SSIM local variance of the image
    normals: wp.array  # [C,H,W] vec3, unit normal of the target depth per quad, 0 = none
    inv_depth_count: wp.array  # [C] float, 1 / #pixels with a target depth (0: none)
    sources: tuple  # (images, depths, sky) host objects it was made from
    sky: wp.array | None = None  # [C,H,W] float, 1 / (camera's pixels) on its sky, 0 elsewhere; None: no sky


@dataclass
class LossResult:
    """Device outputs of :meth:`MappingLoss.__call__`; overwritten by its next call."""

    grad_color: wp.array  # [C,H,W] vec3, dL/d rendered colour
    grad_depth: wp.array  # [C,H,W] float, dL/d rendered depth (1/m)
    grad_exposure: wp.array  # [C,2] float, dL/d (log a, b)
    losses: wp.array  # [C] vec4d: colour, depth and normal terms (weighted), mean squared error

    def values(self) -> tuple[float, np.ndarray]:
        """Host copy: (total loss, PSNR [C] in dB of the clipped exposed render)."""
        v = self.losses.numpy()
        with np.errstate(divide="ignore"):
            psnr = np.where(v[:, 3] > 0, -10.0 * np.log10(v[:, 3]), np.inf)
        return float(v[:, :3].sum()), psnr


def pad_images(images, C: int, H: int, W: int, channels: int = 0) -> np.ndarray:
    """Stack per-camera host images ([h_c,w_c(,3)], ``None`` = zeros) into [C,H,W(,3)] float32."""
    out = np.zeros((C, H, W, channels) if channels else (C, H, W), np.float32)
    for c, img in enumerate(images):
        if img is not None:
            img = np.asarray(img)
            out[c, : img.shape[0], : img.shape[1]] = img
    return out


class MappingLoss:
    """The device loss of a batch of C views (one keyframe's rig views).

    ``cameras``: the C full-resolution :class:`Camera` structs (their sizes bound each
    view; images are padded to the largest). ``cache_bytes``: device memory the keyframes
    whose targets stay on the device may take (at least 2 keyframes; :attr:`cache_size`
    of them). Work buffers are allocated once and reused by every call."""

    def __init__(self, cameras: list, device=None, cache_bytes: int = CACHE_BYTES, rays=None):
        from ..kernels import losses as loss_kernels
        from ..kernels.ba import grid_rays_kernel

        self.device = wp.get_device(device)
        wp.load_module(loss_kernels, device=self.device)  # once, here: not from the row-band threads
        self.C = len(cameras)
        self.H = max(c.height for c in cameras)
        self.W = max(c.width for c in cameras)
        self.cameras = wp.array(cameras, dtype=Camera, device=self.device)
        self.window = wp.array(ssim_window(), dtype=float, device=self.device)
        if rays is None:  # unit-depth ray per pixel [C,H,W] (or the keyframe buffer's, passed in)
            rays = wp.zeros(self.shape, dtype=wp.vec3, device=self.device)
            wp.launch(grid_rays_kernel, dim=self.shape, inputs=[self.cameras], outputs=[rays], device=self.device)
        elif tuple(rays.shape) != tuple(self.shape) or rays.device != self.device:
            raise ValueError(f"MappingLoss: rays must be {tuple(self.shape)} on {self.device}, got {tuple(rays.shape)} on {rays.device}")
        self.rays = rays
        self._no_ray = ~np.isfinite(rays.numpy()).all(-1)  # [C,H,W]: pixels without a ray get no depth target
        #: device bytes of one keyframe's targets: image, SSIM mean and variance, normals (vec3), depth, sky
        self.keyframe_bytes = self.C * self.H * self.W * 4 * (4 * 3 + 2)
        self.cache_size = max(2, int(cache_bytes) // self.keyframe_bytes)
        self._cache: OrderedDict[int, KeyframeTargets] = OrderedDict()
        vec3_maps = [wp.zeros(self.shape, dtype=wp.vec3, device=self.device) for _ in range(8)]
        self._h = vec3_maps[0:3]  # horizontal passes
        self._d = vec3_maps[3:6]  # moment adjoints
        self._quad = vec3_maps[6:8]  # normal adjoints per quad
        self.segment = CUDA_SEGMENT if self.device.is_cuda else self.W
        self._segments = wp.zeros((self.C, self.H, -(-self.W // self.segment)), dtype=vec8d, device=self.device)
        self._sums = wp.zeros(self.C, dtype=vec8d, device=self.device)
        self._normal_weight = wp.zeros(self.C, dtype=float, device=self.device)
        self.result = LossResult(
            wp.zeros(self.shape, dtype=wp.vec3, device=self.device),
            wp.zeros(self.shape, dtype=float, device=self.device),
            wp.zeros((self.C, 2), dtype=float, device=self.device),
            wp.zeros(self.C, dtype=wp.vec4d, device=self.device),
        )

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.C, self.H, self.W)

    def _rows_launch(self, kernel, inputs, outputs, width=None) -> None:
        """Launch a kernel of dim ``(C, rows, width)`` (default: the image width) over bands of rows."""
        dims = (self.C, self.W if width is None else width)

        def band(worker, row0, rows):
            wp.launch(kernel, dim=(dims[0], rows, dims[1]), inputs=[*inputs, row0], outputs=outputs, device=self.device)

        run_row_bands(self.device, self.H, band)

    # ----------------------------------------------------------------------------------
    def make_targets(self, images, depths, sky=None) -> KeyframeTargets:
        """Upload one keyframe's targets: ``images[c]`` [h_c,w_c,3] in [0,1] (float, or 8-bit as
        the keyframe buffer stores it: :func:`~mcgs_warp.buffer.float_image`), ``depths[c]``
        [h_c,w_c] m (0 or ``None`` = none) per camera; precompute the target-only SSIM
        statistics and normals. ``sky[c]`` ([h_c,w_c] bool or ``None``): pixels that get no
        depth target and the sky term (:mod:`mcgs_warp.mapping.sky`)."""
        dev, C, H, W = self.device, self.C, self.H, self.W
        depths = list(depths) if depths is not None else [None] * C
        img = wp.array(pad_images([float_image(im) for im in images], C, H, W, 3), dtype=wp.vec3, device=dev)
        dep_np = pad_images(depths, C, H, W)
        dep_np[self._no_ray] = 0.0
        sky_arr = None
        if sky is not None and any(m is not None and np.any(m) for m in sky):
            sky_np = pad_images([None if m is None else np.asarray(m, np.float32) for m in sky], C, H, W)
            dep_np[sky_np > 0] = 0.0
            sky_np *= np.array([1.0 / (img_c.shape[0] * img_c.shape[1]) for img_c in images], np.float32)[:, None, None]
            sky_arr = wp.array(sky_np, dtype=float, device=dev)
        dep = wp.array(dep_np, dtype=float, device=dev)
        counts = (dep_np > 0).sum(axis=(1, 2))
        inv_count = np.where(counts > 0, 1.0 / np.maximum(counts, 1), 0.0).astype(np.float32)
        t = KeyframeTargets(
            img,
            dep,
            wp.zeros(self.shape, dtype=wp.vec3, device=dev),
            wp.zeros(self.shape, dtype=wp.vec3, device=dev),
            wp.zeros(self.shape, dtype=wp.vec3, device=dev),
            wp.array(inv_count, dtype=float, device=dev),
            (images, depths, sky),
            sky_arr,
        )
        h_t, h_tt = self._h[0], self._h[1]
        self._rows_launch(ssim_target_rows_kernel, [img, self.cameras, self.window], [h_t, h_tt])
        self._rows_launch(ssim_target_kernel, [self.cameras, self.window], [h_t, h_tt, t.mu, t.var])
        self._rows_launch(target_normals_kernel, [dep, self.rays, self.cameras], [t.normals])
        return t

    def targets(self, key, images, depths, sky=None) -> KeyframeTargets:
        """The cached targets of keyframe ``key``, made (or remade, when ``images``,
        ``depths`` or ``sky`` are other objects than last time) by :meth:`make_targets`."""
        t = self._cache.get(key)
        if t is None or not (_same(t.sources[0], images) and _same(t.sources[1], depths) and _same(t.sources[2], sky)):
            t = self.make_targets(images, depths, sky)
        self._cache[key] = t
        self._cache.move_to_end(key)
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return t

    def forget(self, key=None) -> None:
        """Drop the cached targets of ``key`` (all with ``None``)."""
        if key is None:
            self._cache.clear()
        else:
            self._cache.pop(key, None)

    # ----------------------------------------------------------------------------------
    def __call__(self, color, depth, targets: KeyframeTargets, exposure, lambda_ssim: float, lambda_depth: float, lambda_normal: float) -> LossResult:
        """Loss and gradients of rendered ``color`` [C,H,W] vec3 and ``depth`` [C,H,W]
        (m) against ``targets`` with ``exposure`` [C,2] float (log a, b) per camera
        (device arrays). Everything stays on the device; see :meth:`LossResult.values`."""
        dev, cams, win = self.device, self.cameras, self.window
        for name, arr in (("color", color), ("depth", depth), ("exposure", exposure), ("targets.image", targets.image)):
            if arr.device != dev:  # a kernel would read another device's memory (a crash, not an error)
                raise ValueError(f"MappingLoss on {dev}: {name} is on {arr.device}")
        r = self.result
        h, d, qa, qb = self._h, self._d, self._quad[0], self._quad[1]
        ls, ld = float(lambda_ssim), float(lambda_depth)
        if ls > 0:
            self._rows_launch(ssim_moments_rows_kernel, [color, targets.image, exposure, cams, win], h)
        seg, n_seg = self.segment, self._segments.shape[2]
        self._rows_launch(
            loss_terms_kernel,
            [color, depth, targets.image, targets.depth, targets.mu, targets.var, targets.normals, self.rays, exposure, cams, win, ls, seg],
            [*h, *d, qa, qb, self._segments],
            n_seg,
        )
        wp.launch(camera_sums_kernel, dim=self.C, inputs=[self._segments, cams], outputs=[self._sums], device=dev)
        wp.launch(loss_summary_kernel, dim=self.C, inputs=[self._sums, cams, targets.inv_depth_count, ls, ld, float(lambda_normal)], outputs=[r.losses, self._normal_weight], device=dev)
        if ls > 0:
            self._rows_launch(blur_rows3_kernel, [cams, win], [*d, *h])
        self._rows_launch(
            image_grad_kernel,
            [color, depth, targets.image, targets.depth, self.rays, exposure, cams, win, ls, ld, targets.inv_depth_count, self._normal_weight, seg],
            [*h, qa, qb, r.grad_color, r.grad_depth, self._segments],
            n_seg,
        )
        wp.launch(camera_sums_kernel, dim=self.C, inputs=[self._segments, cams], outputs=[self._sums], device=dev)
        wp.launch(exposure_grad_kernel, dim=self.C, inputs=[self._sums], outputs=[r.grad_exposure], device=dev)
        return r


def _same(a, b) -> bool:
    """Whether two lists of per-camera arrays are the same objects (not merely equal)."""
    if a is b:
        return True
    if a is None or b is None or len(a) != len(b):
        return False
    return all(x is y for x, y in zip(a, b))
