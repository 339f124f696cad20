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

On the CPU both passes run one thread per tile instead (:func:`blend_tiles_kernel`,
:func:`blend_backward_tiles_kernel`): the tile's list is walked once and each splat
visits only the pixels of its box, about a quarter of the pixel-splat tests of the
per-pixel form for the built-in sequence's maps (2x faster forward, 1.5x backward);
images are bitwise those of the per-pixel form. CUDA keeps one thread per pixel.

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
    out_median: wp.array(dtype=float, ndim=3),  # [C,H,W] m: median depth (0 where alpha stays below 0.5)
):
    c, yb, x = wp.tid()
    y = yb + row0
    cam = cameras[c]
    color = wp.vec3(0.0)
    dacc = float(0.0)
    median = float(0.0)
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
            if T >= 0.5 and next_T < 0.5:
                median = r[7]  # the splat where the transmittance crosses 0.5
            T = next_T
            last = j - start + 1
    out_median[c, y, x] = median
    out_color[c, y, x] = color
    a = 1.0 - T
    if a > 0.0:
        out_depth[c, y, x] = dacc / a
    else:
        out_depth[c, y, x] = 0.0
    out_alpha[c, y, x] = a
    out_T[c, y, x] = T
    n_contrib[c, y, x] = last


@wp.func
def camera_tile_row(row: int, tiles_per_camera: int, tiles_x: int):
    """Camera and tile row of the tile blenders' launch row ``row`` (rows count the
    (camera, tile row) pairs camera-major, so CPU bands of them balance across cameras)."""
    tiles_y = tiles_per_camera // tiles_x
    c = row // tiles_y
    return c, row - c * tiles_y


@wp.func
def splat_box(r: splat_record, x0: int, y0: int, x1: int, y1: int):
    """Pixel box ``(bx0, by0, bx1, by1)`` (inclusive, clipped to ``[x0, x1) x [y0, y1)``)
    outside which :func:`splat_alpha` is 0: the ellipse ``d^T conic d <= min(9, support)``
    spans ``sqrt(m conic_c / det)`` in x and ``sqrt(m conic_a / det)`` in y, enlarged so
    that float32 rounding never drops a pixel (extra pixels are tested anyway): besides a
    fixed margin, by ``1e-6 conic_a conic_c / det``, the relative error of
    :func:`splat_alpha`'s ``m`` for long thin slanted splats, whose terms cancel."""
    m = wp.min(r[5], MAX_MAHALANOBIS2)
    det = r[2] * r[4] - r[3] * r[3]
    grow = 1.001 + 1.0e-6 * r[2] * r[4] / det
    hx = wp.sqrt(m * r[4] / det) * grow + 0.01
    hy = wp.sqrt(m * r[2] / det) * grow + 0.01
    bx0 = wp.max(x0, int(wp.ceil(r[0] - hx)))
    bx1 = wp.min(x1 - 1, int(wp.floor(r[0] + hx)))
    by0 = wp.max(y0, int(wp.ceil(r[1] - hy)))
    by1 = wp.min(y1 - 1, int(wp.floor(r[1] + hy)))
    return bx0, by0, bx1, by1


#: One pixel's running state in the tile blender: transmittance (negated once the pixel
#: is finished), colour sum (3), depth sum, entries walked to the last contributor, median depth.
blend_state = wp.types.vector(length=7, dtype=wp.float32)


@wp.kernel
def blend_tiles_kernel(
    records: wp.array(dtype=splat_record),
    record_colors: wp.array(dtype=wp.vec3),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    cameras: wp.array(dtype=Camera),
    tiles_x: int,
    tiles_per_camera: int,
    row0: int,  # first (camera, tile row) of this launch, counted camera-major
    state: wp.array(dtype=blend_state, ndim=3),  # [C,H,W] scratch
    out_color: wp.array(dtype=wp.vec3, ndim=3),
    out_depth: wp.array(dtype=float, ndim=3),
    out_alpha: wp.array(dtype=float, ndim=3),
    out_T: wp.array(dtype=float, ndim=3),
    n_contrib: wp.array(dtype=wp.int32, ndim=3),
    out_median: wp.array(dtype=float, ndim=3),
):
    """:func:`blend_kernel` with one thread per tile (the CPU's form, launched over
    ``(C * tiles_y, tiles_x)``, camera-major, so that bands of rows balance across
    cameras): the tile's list is walked once and each splat visits only the pixels of its
    box (:func:`splat_box`), about a quarter of the tile's; every pixel sees the same
    operations in the same order as in :func:`blend_kernel`, so the images are bitwise
    equal. Each pixel's running sums live in one ``state`` entry (:data:`blend_state`,
    one load and one store per splat-pixel pair) and reach the outputs at the end."""
    u, tx = wp.tid()
    c, ty = camera_tile_row(u + row0, tiles_per_camera, tiles_x)
    cam = cameras[c]
    H = out_color.shape[1]
    W = out_color.shape[2]
    x0 = tx * TILE_SIZE
    y0 = ty * TILE_SIZE
    if x0 >= W or y0 >= H:
        return
    xe = wp.min(x0 + TILE_SIZE, W)
    ye = wp.min(y0 + TILE_SIZE, H)
    for y in range(y0, ye):
        for x in range(x0, xe):
            state[c, y, x] = blend_state(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    x1 = wp.min(xe, cam.width)
    y1 = wp.min(ye, cam.height)
    if x0 < x1 and y0 < y1:
        tile = c * tiles_per_camera + ty * tiles_x + tx
        start = tile_start[tile]
        end = tile_end[tile]
        alive = (x1 - x0) * (y1 - y0)  # pixels still blending
        for j in range(start, end):
            if alive == 0:
                break
            r = records[j]
            cj = record_colors[j]
            rank = float(j - start + 1)
            bx0, by0, bx1, by1 = splat_box(r, x0, y0, x1, y1)
            for y in range(by0, by1 + 1):
                for x in range(bx0, bx1 + 1):
                    st = state[c, y, x]
                    T = st[0]
                    if T < 0.0:
                        continue  # finished: the transmittance would fall below T_MIN
                    alpha, g = splat_alpha(r, float(x), float(y))
                    if alpha < ALPHA_MIN:
                        continue
                    next_T = T * (1.0 - alpha)
                    if next_T < T_MIN:
                        st[0] = -T
                        state[c, y, x] = st
                        alive -= 1
                        continue
                    w = alpha * T
                    color = wp.vec3(st[1], st[2], st[3]) + w * cj
                    median = st[6]
                    if T >= 0.5 and next_T < 0.5:
                        median = r[7]  # the splat where the transmittance crosses 0.5
                    state[c, y, x] = blend_state(next_T, color[0], color[1], color[2], st[4] + w * r[7], rank, median)
    for y in range(y0, ye):
        for x in range(x0, xe):
            st = state[c, y, x]
            T = wp.abs(st[0])
            a = 1.0 - T
            out_color[c, y, x] = wp.vec3(st[1], st[2], st[3])
            if a > 0.0:
                out_depth[c, y, x] = st[4] / a
            else:
                out_depth[c, y, x] = 0.0
            out_alpha[c, y, x] = a
            out_T[c, y, x] = T
            n_contrib[c, y, x] = int(st[5])
            out_median[c, y, x] = st[6]


#: The tile backward's constants of one pixel: dL/dC (3), dL/d depth sum, the depth sum,
#: dL/d alpha times the final transmittance, dL/dC . C, and n_contrib (as a float).
pixel_terms = wp.types.vector(length=8, dtype=wp.float32)


@wp.func
def backward_pixel_terms(
    out_color: wp.array(dtype=wp.vec3, ndim=3),
    out_depth: wp.array(dtype=float, ndim=3),
    out_alpha: wp.array(dtype=float, ndim=3),
    out_T: wp.array(dtype=float, ndim=3),
    n_contrib: wp.array(dtype=wp.int32, ndim=3),
    grad_color: wp.array(dtype=wp.vec3, ndim=3),
    grad_depth: wp.array(dtype=float, ndim=3),
    grad_alpha: wp.array(dtype=float, ndim=3),
    c: int,
    y: int,
    x: int,
):
    """The backward replay's constants of pixel (c, y, x) (:data:`pixel_terms`; all 0 where
    no splat contributed): the normalized depth's and alpha's gradients become gradients
    of the depth sum and, times the final transmittance, of each splat's alpha."""
    n = n_contrib[c, y, x]
    if n == 0:  # then alpha is 0 and nothing is replayed
        return pixel_terms(0.0)
    A = out_alpha[c, y, x]
    Dn = out_depth[c, y, x]
    gd = grad_depth[c, y, x]
    gC = grad_color[c, y, x]
    g_a = grad_alpha[c, y, x] - gd * Dn / A
    return pixel_terms(gC[0], gC[1], gC[2], gd / A, Dn * A, g_a * out_T[c, y, x], wp.dot(out_color[c, y, x], gC), float(n))


@wp.func
def replay_splat(r: splat_record, ci: wp.vec3, alpha: float, g: float, px: float, py: float, T: float, SgC: float, Sd: float, gC: wp.vec3, CgC: float, Dacc: float, g_dacc: float, gaTf: float):
    """One splat's step of the backward replay at pixel ``(px, py)``: its blend weight
    ``w``, the colour sum ``S`` (carried as ``SgC = dL/dC . S``: the colour enters the
    gradient only through that dot product) and depth sum ``Sd`` including it, the
    transmittance after it, and the gradients w.r.t. its opacity, conic and 2D mean
    (``shaped`` 0 and no such gradients where alpha is clamped at 0.99). ``CgC = dL/dC . C``
    and ``gaTf = dL/dalpha_pixel * T_final`` are the pixel's constants."""
    o = r[6]
    di = r[7]
    w = alpha * T
    cg = wp.dot(gC, ci)
    SgC_new = SgC + w * cg
    Sd_new = Sd + w * di
    inv1ma = 1.0 / (1.0 - alpha)
    g_alpha = T * cg - (CgC - SgC_new) * inv1ma
    g_alpha += g_dacc * (T * di - (Dacc - Sd_new) * inv1ma)
    g_alpha += gaTf * inv1ma
    T_next = T * (1.0 - alpha)
    if o * g > ALPHA_MAX:
        return w, SgC_new, Sd_new, T_next, 0.0, wp.vec3(0.0), wp.vec2(0.0), 0
    g_m = -0.5 * g_alpha * o * g  # dL/dm, m = d^T conic d
    dx = px - r[0]
    dy = py - r[1]
    g_conic = g_m * wp.vec3(dx * dx, 2.0 * dx * dy, dy * dy)
    g_mean = -2.0 * g_m * wp.vec2(r[2] * dx + r[3] * dy, r[3] * dx + r[4] * dy)
    return w, SgC_new, Sd_new, T_next, g_alpha * g, g_conic, g_mean, 1


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
    q = backward_pixel_terms(out_color, out_depth, out_alpha, out_T, n_contrib, grad_color, grad_depth, grad_alpha, c, y, x)
    gC = wp.vec3(q[0], q[1], q[2])
    g_dacc = q[3]
    px = float(x)
    py = float(y)
    T = float(1.0)
    SgC = float(0.0)
    Sd = float(0.0)
    for j in range(start, start + n):
        r = records[j]
        alpha, g = splat_alpha(r, px, py)
        if alpha < ALPHA_MIN:
            continue
        flat = values[j]
        w, SgC, Sd, T, g_opacity, g_conic, g_mean, shaped = replay_splat(r, record_colors[j], alpha, g, px, py, T, SgC, Sd, gC, q[6], q[4], g_dacc, q[5])
        wp.atomic_add(grad_colors, flat % n_gaussians, w * gC)
        wp.atomic_add(grad_splat_depth, flat, w * g_dacc)
        if shaped == 1:
            wp.atomic_add(grad_opacity, flat, g_opacity)
            wp.atomic_add(grad_conic, flat, g_conic)
            wp.atomic_add(grad_mean2d, flat, g_mean)


@wp.kernel
def blend_backward_tiles_kernel(
    records: wp.array(dtype=splat_record),
    record_colors: wp.array(dtype=wp.vec3),
    values: wp.array(dtype=wp.int32),
    tile_start: wp.array(dtype=wp.int32),
    cameras: wp.array(dtype=Camera),
    n_gaussians: int,
    tiles_x: int,
    tiles_per_camera: int,
    row0: int,  # first (camera, tile row) of this launch, counted camera-major
    out_color: wp.array(dtype=wp.vec3, ndim=3),  # forward outputs
    out_depth: wp.array(dtype=float, ndim=3),
    out_alpha: wp.array(dtype=float, ndim=3),
    out_T: wp.array(dtype=float, ndim=3),
    n_contrib: wp.array(dtype=wp.int32, ndim=3),
    grad_color: wp.array(dtype=wp.vec3, ndim=3),
    grad_depth: wp.array(dtype=float, ndim=3),
    grad_alpha: wp.array(dtype=float, ndim=3),
    run: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] scratch: transmittance before the splat, dL/dC . colour sum, depth sum
    pixel: wp.array(dtype=pixel_terms, ndim=3),  # [C,H,W] scratch: the pixel's constants
    grad_mean2d: wp.array(dtype=wp.vec2),  # [C*N] out (accumulated)
    grad_conic: wp.array(dtype=wp.vec3),
    grad_opacity: wp.array(dtype=float),
    grad_splat_depth: wp.array(dtype=float),
    grad_colors: wp.array(dtype=wp.vec3),  # [N] out
):
    """:func:`blend_backward_kernel` with one thread per tile (the CPU's form): the replay
    walks the tile's list once, each splat visiting only the pixels of its box
    (:func:`splat_box`) with the per-pixel running sums kept in scratch arrays; each
    splat's gradients are summed over the tile's pixels and added once. The per-pixel
    terms are those of :func:`blend_backward_kernel`; only the summation order (and so float32
    rounding) differs."""
    u, tx = wp.tid()
    c, ty = camera_tile_row(u + row0, tiles_per_camera, tiles_x)
    cam = cameras[c]
    x0 = tx * TILE_SIZE
    y0 = ty * TILE_SIZE
    x1 = wp.min(x0 + TILE_SIZE, cam.width)
    y1 = wp.min(y0 + TILE_SIZE, cam.height)
    if x0 >= x1 or y0 >= y1:
        return
    n_max = int(0)
    for y in range(y0, y1):
        for x in range(x0, x1):
            run[c, y, x] = wp.vec3(1.0, 0.0, 0.0)
            q = backward_pixel_terms(out_color, out_depth, out_alpha, out_T, n_contrib, grad_color, grad_depth, grad_alpha, c, y, x)
            pixel[c, y, x] = q
            n_max = wp.max(n_max, int(q[7]))
    start = tile_start[c * tiles_per_camera + ty * tiles_x + tx]
    for j in range(start, start + n_max):
        r = records[j]
        bx0, by0, bx1, by1 = splat_box(r, x0, y0, x1, y1)
        ci = record_colors[j]
        hit = int(0)
        acc_color = wp.vec3(0.0)
        acc_depth = float(0.0)
        acc_opacity = float(0.0)
        acc_conic = wp.vec3(0.0)
        acc_mean = wp.vec2(0.0)
        rank = float(j - start)
        for y in range(by0, by1 + 1):
            for x in range(bx0, bx1 + 1):
                q = pixel[c, y, x]
                if rank >= q[7]:
                    continue  # beyond the pixel's last contributor
                px = float(x)
                py = float(y)
                alpha, g = splat_alpha(r, px, py)
                if alpha < ALPHA_MIN:
                    continue
                hit = 1
                gC = wp.vec3(q[0], q[1], q[2])
                s = run[c, y, x]
                w, SgC, Sd, T, g_opacity, g_conic, g_mean, shaped = replay_splat(r, ci, alpha, g, px, py, s[0], s[1], s[2], gC, q[6], q[4], q[3], q[5])
                run[c, y, x] = wp.vec3(T, SgC, Sd)
                acc_color += w * gC
                acc_depth += w * q[3]
                acc_opacity += g_opacity
                acc_conic += g_conic
                acc_mean += g_mean
        if hit == 1:
            flat = values[j]
            wp.atomic_add(grad_colors, flat % n_gaussians, acc_color)
            wp.atomic_add(grad_splat_depth, flat, acc_depth)
            wp.atomic_add(grad_opacity, flat, acc_opacity)
            wp.atomic_add(grad_conic, flat, acc_conic)
            wp.atomic_add(grad_mean2d, flat, acc_mean)
