"""Python entry points of the splatting pipeline: one function per stage, plus
:func:`render` / :func:`render_backward` on top.

``project -> bin_tiles -> blend`` and, backwards, ``blend_backward ->
project_backward``. Every stage takes a batch of C views (a rig, or several
keyframes) so one launch serves all cameras; images of different sizes are
padded to the largest and the padding is left at zero.

Shapes: N Gaussians, C views, H x W the largest image. Arrays are Warp arrays on
the views' device; ``*.numpy()`` gives NumPy views of them on the CPU.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .blend import blend_backward_kernel, blend_backward_tiles_kernel, blend_kernel, blend_tiles_kernel, blend_state, gather_splats_kernel, pixel_terms, splat_record
from .camera import FAR, NEAR, Camera
from .launch import cpu_workers, run_row_bands
from .projection import project_gaussians_backward_kernel, project_gaussians_kernel
from .se3 import vec6
from .tiles import TILE_SIZE, count_tiles_kernel, tile_ranges_kernel, write_tile_keys_kernel


@dataclass
class Gaussians:
    """Structure-of-arrays Gaussian parameters (what the optimizer updates)."""

    means: wp.array  # [N] vec3, world, m
    quats: wp.array  # [N] vec4 (x, y, z, w), normalized when used
    log_scales: wp.array  # [N] vec3, log(m)
    opacity_logits: wp.array  # [N] float, opacity = sigmoid(logit)
    colors: wp.array  # [N] vec3, RGB in [0, 1]

    @classmethod
    def from_numpy(cls, means, quats, log_scales, opacity_logits, colors, device=None) -> "Gaussians":
        """Copy NumPy arrays ([N,3], [N,4] xyzw, [N,3], [N], [N,3]) to ``device``."""
        n = len(means)
        shapes = {"means": (means, 3), "quats": (quats, 4), "log_scales": (log_scales, 3), "colors": (colors, 3)}
        for name, (arr, k) in shapes.items():
            if np.shape(arr) != (n, k):
                raise ValueError(f"Gaussians.{name}: expected shape ({n}, {k}), got {np.shape(arr)}")
        if np.shape(opacity_logits) != (n,):
            raise ValueError(f"Gaussians.opacity_logits: expected shape ({n},), got {np.shape(opacity_logits)}")

        def arr(a, dtype):
            return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=dtype, device=device)

        return cls(
            arr(means, wp.vec3),
            arr(quats, wp.vec4),
            arr(log_scales, wp.vec3),
            arr(opacity_logits, float),
            arr(colors, wp.vec3),
        )

    @property
    def n(self) -> int:
        return self.means.shape[0]

    @property
    def device(self):
        return self.means.device


@dataclass
class Views:
    """A batch of C camera views: intrinsics and world->camera matrices."""

    cameras: wp.array  # [C] Camera
    viewmats: wp.array  # [C] mat44, T_c_w
    width: int  # largest image width, px
    height: int  # largest image height, px

    @classmethod
    def create(cls, cameras: list, T_w_c, device=None) -> "Views":
        """``cameras``: list of :class:`Camera`; ``T_w_c`` [C,4,4]: camera -> world poses (m)."""
        T_w_c = np.asarray(T_w_c, dtype=np.float64).reshape(-1, 4, 4)
        if len(cameras) != len(T_w_c) or len(cameras) == 0:
            raise ValueError(f"Views: expected one pose per camera, got {len(cameras)} cameras, {len(T_w_c)} poses")
        T_c_w = np.linalg.inv(T_w_c).astype(np.float32)
        return cls(
            wp.array(cameras, dtype=Camera, device=device),
            wp.array(T_c_w, dtype=wp.mat44, device=device),
            max(c.width for c in cameras),
            max(c.height for c in cameras),
        )

    @property
    def n(self) -> int:
        return self.cameras.shape[0]

    @property
    def device(self):
        return self.cameras.device

    @property
    def tiles_x(self) -> int:
        return (self.width + TILE_SIZE - 1) // TILE_SIZE

    @property
    def tiles_y(self) -> int:
        return (self.height + TILE_SIZE - 1) // TILE_SIZE


@dataclass
class Projection:
    """Per (view, Gaussian) splats, index ``c * N + i``."""

    mean2d: wp.array  # [C*N] vec2, px
    conic: wp.array  # [C*N] vec3, inverse 2D covariance (a, b, c), 1/px^2
    depth: wp.array  # [C*N] float, m
    opacity: wp.array  # [C*N] float
    visible: wp.array  # [C*N] int32, 0 where culled
    n_gaussians: int


@dataclass
class TileBins:
    """Depth-sorted splat lists per tile; ``values[tile_start[t]:tile_end[t]]``."""

    keys: wp.array  # [2*count] int64, tile << 32 | depth bits (first count sorted)
    values: wp.array  # [2*count] int32, flat splat index
    count: int  # number of (splat, tile) overlaps
    tile_start: wp.array  # [C*tiles] int32
    tile_end: wp.array  # [C*tiles] int32


@dataclass
class Rendered:
    """Blended images [C,H,W] and what the backward pass needs."""

    color: wp.array  # [C,H,W] vec3, RGB without background
    depth: wp.array  # [C,H,W] float, m, normalized by alpha (0 where empty)
    alpha: wp.array  # [C,H,W] float, coverage 1 - T
    transmittance: wp.array  # [C,H,W] float, final T
    n_contrib: wp.array  # [C,H,W] int32, list entries walked up to the last contributor
    median_depth: wp.array  # [C,H,W] float, m: depth of the splat where the transmittance crosses 0.5 (0 where alpha stays below 0.5; no adjoint)
    projection: Projection
    bins: TileBins
    records: wp.array  # [count] splat_record, splats in sorted-list order
    record_colors: wp.array  # [count] vec3, their colours


@dataclass
class Gradients:
    """Gradients of a scalar loss. ``pose[c]`` is dL/dxi for ``T_w_c <- T_w_c @ Exp(xi)``,
    ``xi = (rho, phi)`` in the camera frame; ``mean2d`` (per splat) serves densification."""

    means: wp.array  # [N] vec3
    quats: wp.array  # [N] vec4
    log_scales: wp.array  # [N] vec3
    opacity_logits: wp.array  # [N] float
    colors: wp.array  # [N] vec3
    pose: wp.array  # [C] vec6
    mean2d: wp.array  # [C*N] vec2


def project(gaussians: Gaussians, views: Views, near: float = NEAR, far: float = FAR) -> Projection:
    """EWA-project every Gaussian into every view (culling outside near/far and the camera's domain)."""
    n, dev = gaussians.n, views.device
    total = views.n * n
    out = Projection(
        wp.zeros(total, dtype=wp.vec2, device=dev),
        wp.zeros(total, dtype=wp.vec3, device=dev),
        wp.zeros(total, dtype=float, device=dev),
        wp.zeros(total, dtype=float, device=dev),
        wp.zeros(total, dtype=wp.int32, device=dev),
        n,
    )
    if total:
        wp.launch(
            project_gaussians_kernel,
            dim=total,
            inputs=[
                gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits,
                views.cameras, views.viewmats, n, near, far,
            ],
            outputs=[out.mean2d, out.conic, out.depth, out.opacity, out.visible],
            device=dev,
        )  # fmt: skip
    return out


def bin_tiles(proj: Projection, views: Views) -> TileBins:
    """Key every (splat, overlapped tile) pair by (tile, depth), radix-sort, and find
    each tile's range in the sorted list."""
    dev = views.device
    total = proj.mean2d.shape[0]
    tiles_per_camera = views.tiles_x * views.tiles_y
    n_tiles = views.n * tiles_per_camera
    tile_start = wp.zeros(n_tiles, dtype=wp.int32, device=dev)
    tile_end = wp.zeros(n_tiles, dtype=wp.int32, device=dev)
    empty = TileBins(wp.zeros(0, dtype=wp.int64, device=dev), wp.zeros(0, dtype=wp.int32, device=dev), 0, tile_start, tile_end)
    if total == 0:
        return empty
    counts = wp.empty(total, dtype=wp.int32, device=dev)
    wp.launch(
        count_tiles_kernel,
        dim=total,
        inputs=[proj.mean2d, proj.conic, proj.opacity, proj.visible, views.cameras, proj.n_gaussians],
        outputs=[counts],
        device=dev,
    )
    offsets = wp.empty(total, dtype=wp.int32, device=dev)
    wp.utils.array_scan(counts, offsets, inclusive=True)
    count = int(offsets[total - 1 : total].numpy()[0])
    if count == 0:
        return empty
    keys = wp.empty(2 * count, dtype=wp.int64, device=dev)
    values = wp.empty(2 * count, dtype=wp.int32, device=dev)
    wp.launch(
        write_tile_keys_kernel,
        dim=total,
        inputs=[
            proj.mean2d, proj.conic, proj.opacity, proj.depth, proj.visible, views.cameras,
            proj.n_gaussians, views.tiles_x, tiles_per_camera, offsets,
        ],
        outputs=[keys, values],
        device=dev,
    )  # fmt: skip
    wp.utils.radix_sort_pairs(keys, values, count, 0, 32 + max(1, int(n_tiles - 1).bit_length()))
    wp.launch(tile_ranges_kernel, dim=count, inputs=[keys, count], outputs=[tile_start, tile_end], device=dev)
    return TileBins(keys, values, count, tile_start, tile_end)


def blend(proj: Projection, bins: TileBins, colors: wp.array, views: Views) -> Rendered:
    """Front-to-back alpha blending of every view's pixels."""
    dev = views.device
    shape = (views.n, views.height, views.width)
    records = wp.empty(bins.count, dtype=splat_record, device=dev)
    record_colors = wp.empty(bins.count, dtype=wp.vec3, device=dev)
    if bins.count:
        wp.launch(
            gather_splats_kernel,
            dim=bins.count,
            inputs=[bins.values, proj.mean2d, proj.conic, proj.opacity, proj.depth, colors, proj.n_gaussians],
            outputs=[records, record_colors],
            device=dev,
        )
    out = Rendered(
        wp.empty(shape, dtype=wp.vec3, device=dev),
        wp.empty(shape, dtype=float, device=dev),
        wp.empty(shape, dtype=float, device=dev),
        wp.empty(shape, dtype=float, device=dev),
        wp.empty(shape, dtype=wp.int32, device=dev),
        wp.empty(shape, dtype=float, device=dev),
        proj,
        bins,
        records,
        record_colors,
    )
    tiles = (views.tiles_x, views.tiles_x * views.tiles_y)

    outputs = [out.color, out.depth, out.alpha, out.transmittance, out.n_contrib, out.median_depth]
    if dev.is_cuda:  # one thread per pixel
        wp.launch(blend_kernel, dim=shape, inputs=[records, record_colors, bins.tile_start, bins.tile_end, views.cameras, *tiles, 0], outputs=outputs, device=dev)
        return out

    state = wp.empty(shape, dtype=blend_state, device=dev)  # scratch

    def band(worker, row0, rows):  # CPU: one thread per tile, bands of (camera, tile row) on all cores
        wp.launch(blend_tiles_kernel, dim=(rows, views.tiles_x), inputs=[records, record_colors, bins.tile_start, bins.tile_end, views.cameras, *tiles, row0, state], outputs=outputs, device=dev)

    run_row_bands(dev, views.n * views.tiles_y, band)
    return out


def render(gaussians: Gaussians, views: Views, near: float = NEAR, far: float = FAR) -> Rendered:
    """Render colour, depth and alpha of every view: ``project -> bin_tiles -> blend``."""
    proj = project(gaussians, views, near, far)
    return blend(proj, bin_tiles(proj, views), gaussians.colors, views)


def _image_grad(grad, shape, dtype, dev):
    if grad is None:
        return wp.zeros(shape, dtype=dtype, device=dev)
    if isinstance(grad, wp.array):
        return grad
    return wp.array(np.ascontiguousarray(grad, dtype=np.float32), dtype=dtype, device=dev)


@dataclass
class SplatGradients:
    """Gradients w.r.t. the 2D splats (what :func:`blend_backward` gives)."""

    mean2d: wp.array  # [C*N] vec2
    conic: wp.array  # [C*N] vec3
    opacity: wp.array  # [C*N] float
    depth: wp.array  # [C*N] float
    colors: wp.array  # [N] vec3


def blend_backward(rendered: Rendered, views: Views, grad_color=None, grad_depth=None, grad_alpha=None) -> SplatGradients:
    """Adjoint of :func:`blend`: image gradients (``grad_color`` [C,H,W,3], ``grad_depth``
    [C,H,W] on the normalized depth, ``grad_alpha`` [C,H,W]; NumPy or Warp arrays, ``None``
    for zero) to gradients w.r.t. each splat's 2D mean, conic, opacity, depth and colour."""
    dev = views.device
    shape = (views.n, views.height, views.width)
    gC = _image_grad(grad_color, shape, wp.vec3, dev)
    gD = _image_grad(grad_depth, shape, float, dev)
    gA = _image_grad(grad_alpha, shape, float, dev)
    proj, bins = rendered.projection, rendered.bins
    n, total = proj.n_gaussians, proj.mean2d.shape[0]

    def zeros():
        return SplatGradients(
            wp.zeros(total, dtype=wp.vec2, device=dev),
            wp.zeros(total, dtype=wp.vec3, device=dev),
            wp.zeros(total, dtype=float, device=dev),
            wp.zeros(total, dtype=float, device=dev),
            wp.zeros(n, dtype=wp.vec3, device=dev),
        )

    out = zeros()
    if bins.count == 0:
        return out
    inputs = [
        rendered.records, rendered.record_colors, bins.values, bins.tile_start, views.cameras, n,
        views.tiles_x, views.tiles_x * views.tiles_y,
    ]  # fmt: skip
    forward = [rendered.color, rendered.depth, rendered.alpha, rendered.transmittance, rendered.n_contrib, gC, gD, gA]
    if dev.is_cuda:  # one thread per pixel
        wp.launch(blend_backward_kernel, dim=shape, inputs=[*inputs, 0, *forward], outputs=[out.mean2d, out.conic, out.opacity, out.depth, out.colors], device=dev)
        return out
    # Warp's CPU atomics are plain adds, so each CPU worker accumulates into buffers of
    # its own, summed afterwards in worker order (deterministic for a worker count).
    per_worker = [out] + [zeros() for _ in range(1, cpu_workers())]
    scratch = [wp.empty(shape, dtype=wp.vec3, device=dev), wp.empty(shape, dtype=pixel_terms, device=dev)]

    def band(worker, row0, rows):  # CPU: one thread per tile, bands of (camera, tile row) on all cores
        g = per_worker[worker]
        wp.launch(
            blend_backward_tiles_kernel,
            dim=(rows, views.tiles_x),
            inputs=[*inputs, row0, *forward, *scratch],
            outputs=[g.mean2d, g.conic, g.opacity, g.depth, g.colors],
            device=dev,
        )

    used = run_row_bands(dev, views.n * views.tiles_y, band)
    for g in per_worker[1:used]:
        for name in ("mean2d", "conic", "opacity", "depth", "colors"):
            getattr(out, name).numpy()[...] += getattr(g, name).numpy()  # CPU only: zero-copy views
    return out


def project_backward(gaussians: Gaussians, views: Views, proj: Projection, splat_grads: SplatGradients) -> Gradients:
    """Adjoint of :func:`project`: splat gradients to Gaussian parameters and camera poses."""
    dev = views.device
    n, total = gaussians.n, proj.mean2d.shape[0]
    grads = Gradients(
        wp.zeros(n, dtype=wp.vec3, device=dev),
        wp.zeros(n, dtype=wp.vec4, device=dev),
        wp.zeros(n, dtype=wp.vec3, device=dev),
        wp.zeros(n, dtype=float, device=dev),
        splat_grads.colors,
        wp.zeros(views.n, dtype=vec6, device=dev),
        splat_grads.mean2d,
    )
    if total:
        g = splat_grads
        wp.launch(
            project_gaussians_backward_kernel,
            dim=total,
            inputs=[
                gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits,
                views.cameras, views.viewmats, n, proj.visible, proj.opacity,
                g.mean2d, g.conic, g.depth, g.opacity,
            ],
            outputs=[grads.means, grads.quats, grads.log_scales, grads.opacity_logits, grads.pose],
            device=dev,
        )  # fmt: skip
    return grads


def render_backward(
    gaussians: Gaussians,
    views: Views,
    rendered: Rendered,
    grad_color=None,
    grad_depth=None,
    grad_alpha=None,
) -> Gradients:
    """Gradients of a loss given its gradients w.r.t. the rendered images
    (``grad_color`` [C,H,W,3], ``grad_depth`` [C,H,W], ``grad_alpha`` [C,H,W];
    NumPy or Warp arrays, ``None`` for zero): ``blend_backward -> project_backward``."""
    splat_grads = blend_backward(rendered, views, grad_color, grad_depth, grad_alpha)
    return project_backward(gaussians, views, rendered.projection, splat_grads)
