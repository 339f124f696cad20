"""Front-to-back alpha blending of binned splats, and its adjoint.

One thread per pixel of each camera, launched over ``(C, H, W)``. A pixel walks
its tile's depth-sorted list and, for each splat (DESIGN.md numerics):

* ``m = d^T conic d`` with ``d = pixel - mean2d`` (pixel centres at integers);
  skipped when ``m > 9`` (3 sigma);
* ``alpha = min(0.99, opacity * exp(-m/2))``; skipped when ``alpha < 1/255``;
* stops before a splat that would drop the transmittance ``T`` below ``1e-4``;
* ``color += c alpha T``, ``depth_acc += d alpha T``, ``T *= 1 - alpha``.

Outputs per pixel: colour (no background), depth normalized by the alpha
(``depth_acc / (1 - T)``, 0 where nothing was hit), alpha ``1 - T``, the final
``T`` and ``n_contrib``, the number of list entries walked up to the last
contributor, which bounds the backward replay.

The backward pass replays front to back: with ``S_i`` the colour accumulated up
to and including splat i, ``dC/dalpha_i = c_i T_i - (C - S_i) / (1 - alpha_i)``,
and ``d(1 - T)/dalpha_i = T_final / (1 - alpha_i)``; no division by the
transmittance is needed.
"""

from __future__ import annotations

import warp as wp

from .camera import Camera
from .projection import ALPHA_MIN
from .tiles import MAX_MAHALANOBIS2, TILE_SIZE, support_mahalanobis2

# Hand-written adjoints only: skip Warp's generated backward code (faster compiles).
wp.set_module_options({"enable_backward": False, "optimization_level": 3})

ALPHA_MAX = wp.constant(0.99)
T_MIN = wp.constant(1.0e-4)

#: One splat as the blender reads it, gathered in sorted-list order so each tile's
#: list is one contiguous run: (mean x, mean y, conic a, b, c, support m^2 bound,
#: opacity, depth); 32 bytes, read for every list entry. Colours (read only for
#: contributing entries) are gathered beside it.
splat_record = wp.types.vector(length=8, dtype=wp.float32)


@wp.kernel
def gather_splats_kernel(
    values: wp.array(dtype=wp.int32),  # sorted flat indices
    mean2d: wp.array(dtype=wp.vec2),
    conic: wp.array(dtype=wp.vec3),
    opacity: wp.array(dtype=float),
    depth: wp.array(dtype=float),
    colors: wp.array(dtype=wp.vec3),  # [N]
    n_gaussians: int,
    records: wp.array(dtype=splat_record),  # [count] out
    record_colors: wp.array(dtype=wp.vec3),  # [count] out
):
    j = wp.tid()
    flat = values[j]
    mu = mean2d[flat]
    q = conic[flat]
    o = opacity[flat]
    records[j] = splat_record(mu[0], mu[1], q[0], q[1], q[2], support_mahalanobis2(o), o, depth[flat])
    record_colors[j] = colors[flat % n_gaussians]


@wp.func
def splat_alpha(r: splat_record, px: float, py: float):
    """``(alpha, gaussian)`` of one splat at pixel ``(px, py)``; alpha 0 outside 3 sigma
    or where it cannot reach 1/255 (checked before the exponential, which is costly)."""
    dx = px - r[0]
    dy = py - r[1]
    m = r[2] * dx * dx + 2.0 * r[3] * dx * dy + r[4] * dy * dy
    if m > r[5] or m > MAX_MAHALANOBIS2:
        return 0.0, 0.0
    g = wp.exp(-0.5 * m)
    return wp.min(ALPHA_MAX, r[6] * g), g


@wp.kernel
def blend_kernel(
    records: wp.array(dtype=splat_record),  # [count] in sorted-list order
    record_colors: wp.array(dtype=wp.vec3),  # [count]
    tile_start: wp.array(dtype=wp.int32),  # [C*tiles]
    tile_end: wp.array(dtype=wp.int32),  # [C*tiles]
    cameras: wp.array(dtype=Camera),  # [C]
    tiles_x: int,
    tiles_per_camera: int,
    row0: int,  # first image row of this launch (the launch covers a band of rows)
    out_color: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W]
    out_depth: wp.array(dtype=float, ndim=3),  # [C,H,W] m
    out_alpha: wp.array(dtype=float, ndim=3),  # [C,H,W]
    out_T: wp.array(dtype=float, ndim=3),  # [C,H,W] final transmittance
    n_contrib: wp.array(dtype=wp.int32, ndim=3),  # [C,H,W]
):
    c, yb, x = wp.tid()
    y = yb + row0
    cam = cameras[c]
    color = wp.vec3(0.0)
    dacc = float(0.0)
    T = float(1.0)
    last = int(0)
    if x < cam.width and y < cam.height:
        tile = c * tiles_per_camera + (y // TILE_SIZE) * tiles_x + x // TILE_SIZE
        start = tile_start[tile]
        end = tile_end[tile]
        px = float(x)
        py = float(y)
        for j in range(start, end):
            r = records[j]
            alpha, g = splat_alpha(r, px, py)
            if alpha < ALPHA_MIN:
                continue
            next_T = T * (1.0 - alpha)
            if next_T < T_MIN:
                break
            w = alpha * T
            color += w * record_colors[j]
            dacc += w * r[7]
            T = next_T
            last = j - start + 1
    out_color[c, y, x] = color
    a = 1.0 - T
    if a > 0.0:
        out_depth[c, y, x] = dacc / a
    else:
        out_depth[c, y, x] = 0.0
    out_alpha[c, y, x] = a
    out_T[c, y, x] = T
    n_contrib[c, y, x] = last


@wp.kernel
def blend_backward_kernel(
    records: wp.array(dtype=splat_record),
    record_colors: wp.array(dtype=wp.vec3),
    values: wp.array(dtype=wp.int32),
    tile_start: wp.array(dtype=wp.int32),
    cameras: wp.array(dtype=Camera),
    n_gaussians: int,
    tiles_x: int,
    tiles_per_camera: int,
    row0: int,
    out_color: wp.array(dtype=wp.vec3, ndim=3),  # forward outputs
    out_depth: wp.array(dtype=float, ndim=3),
    out_alpha: wp.array(dtype=float, ndim=3),
    out_T: wp.array(dtype=float, ndim=3),
    n_contrib: wp.array(dtype=wp.int32, ndim=3),
    grad_color: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] dL/d colour
    grad_depth: wp.array(dtype=float, ndim=3),  # [C,H,W] dL/d normalized depth
    grad_alpha: wp.array(dtype=float, ndim=3),  # [C,H,W] dL/d alpha
    grad_mean2d: wp.array(dtype=wp.vec2),  # [C*N] out (accumulated)
    grad_conic: wp.array(dtype=wp.vec3),  # [C*N] out
    grad_opacity: wp.array(dtype=float),  # [C*N] out
    grad_splat_depth: wp.array(dtype=float),  # [C*N] out
    grad_colors: wp.array(dtype=wp.vec3),  # [N] out
):
    c, yb, x = wp.tid()
    y = yb + row0
    cam = cameras[c]
    if x >= cam.width or y >= cam.height:
        return
    n = n_contrib[c, y, x]
    if n == 0:
        return
    tile = c * tiles_per_camera + (y // TILE_SIZE) * tiles_x + x // TILE_SIZE
    start = tile_start[tile]
    gC = grad_color[c, y, x]
    C = out_color[c, y, x]
    A = out_alpha[c, y, x]
    Tf = out_T[c, y, x]
    Dn = out_depth[c, y, x]
    Dacc = Dn * A
    g_dacc = grad_depth[c, y, x] / A
    g_a = grad_alpha[c, y, x] - grad_depth[c, y, x] * Dn / A
    px = float(x)
    py = float(y)
    T = float(1.0)
    S = wp.vec3(0.0)
    Sd = float(0.0)
    for j in range(start, start + n):
        r = records[j]
        alpha, g = splat_alpha(r, px, py)
        if alpha < ALPHA_MIN:
            continue
        flat = values[j]
        i = flat % n_gaussians
        ci = record_colors[j]
        di = r[7]
        o = r[6]
        w = alpha * T
        wp.atomic_add(grad_colors, i, w * gC)
        wp.atomic_add(grad_splat_depth, flat, w * g_dacc)
        S += w * ci
        Sd += w * di
        inv1ma = 1.0 / (1.0 - alpha)
        g_alpha = wp.dot(gC, T * ci - (C - S) * inv1ma)
        g_alpha += g_dacc * (T * di - (Dacc - Sd) * inv1ma)
        g_alpha += g_a * Tf * inv1ma
        T = T * (1.0 - alpha)
        if o * g > ALPHA_MAX:
            continue  # alpha clamped at 0.99: no gradient to opacity or shape
        wp.atomic_add(grad_opacity, flat, g_alpha * g)
        g_m = -0.5 * g_alpha * o * g  # dL/dm, m = d^T conic d
        dx = px - r[0]
        dy = py - r[1]
        wp.atomic_add(grad_conic, flat, g_m * wp.vec3(dx * dx, 2.0 * dx * dy, dy * dy))
        wp.atomic_add(grad_mean2d, flat, -2.0 * g_m * wp.vec2(r[2] * dx + r[3] * dy, r[3] * dx + r[4] * dy))
