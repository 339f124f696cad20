"""Tile binning: one (tile, depth) key per Gaussian-tile overlap, radix-sorted.

Images are cut into ``TILE_SIZE x TILE_SIZE`` pixel tiles; a batch of C cameras
shares one grid of ``tiles_x * tiles_y`` tiles per camera (the largest image),
``tile_global = c * tiles_per_camera + tile``.

Which tiles a Gaussian overlaps is decided exactly, not by a bounding square:
a pixel can receive a Gaussian only where its Mahalanobis distance
``m = d^T Sigma'^-1 d`` satisfies both ``m <= 9`` (the 3-sigma ellipse, DESIGN.md)
and ``opacity * exp(-m/2) >= 1/255``, i.e. ``m <= 2 ln(255 opacity)``
(opacity-aware extent). A tile is kept when that ellipse reaches at least one of
its pixel centres: the minimum of ``m`` over the tile's rectangle of pixel
centres is tested, which culls most tiles of thin, slanted splats. The blending
kernel applies the same two conditions per pixel, so images do not depend on
the tiling (and match the brute-force reference renderer).

Sort keys are ``int64``: ``tile_global << 32 | float_bits(depth)`` (depths are
positive, so their IEEE bits sort like the values; no quantization).
"""

from __future__ import annotations

import warp as wp

from .camera import Camera

# No autodiff through binning: skip Warp's generated backward code (faster compiles).
wp.set_module_options({"enable_backward": False})

TILE_SIZE = wp.constant(16)
#: Largest Mahalanobis distance^2 at which a Gaussian is blended (3 sigma).
MAX_MAHALANOBIS2 = wp.constant(9.0)


@wp.func
def support_mahalanobis2(opacity: float):
    """Mahalanobis distance^2 bounding the pixels a Gaussian of this opacity can reach,
    slightly enlarged so float rounding never drops a tile the blender would use."""
    return wp.min(MAX_MAHALANOBIS2, 2.0 * wp.log(255.0 * opacity)) * 1.0001 + 1.0e-4


@wp.func
def mahalanobis2(conic: wp.vec3, dx: float, dy: float):
    return conic[0] * dx * dx + 2.0 * conic[1] * dx * dy + conic[2] * dy * dy


@wp.func
def _edge_min(conic: wp.vec3, dfix: float, lo: float, hi: float, fixed_is_x: bool):
    # Minimum of m along a rectangle edge where one offset is fixed at dfix and the
    # other ranges over [lo, hi].
    if fixed_is_x:
        t = wp.clamp(-conic[1] * dfix / conic[2], lo, hi)
        return mahalanobis2(conic, dfix, t)
    t = wp.clamp(-conic[1] * dfix / conic[0], lo, hi)
    return mahalanobis2(conic, t, dfix)


@wp.func
def ellipse_reaches_rect(mean: wp.vec2, conic: wp.vec3, k2: float, x0: float, x1: float, y0: float, y1: float):
    """True if ``min over [x0,x1]x[y0,y1]`` of the Mahalanobis distance^2 is ``<= k2``."""
    if mean[0] >= x0 and mean[0] <= x1 and mean[1] >= y0 and mean[1] <= y1:
        return True
    lx = x0 - mean[0]
    hx = x1 - mean[0]
    ly = y0 - mean[1]
    hy = y1 - mean[1]
    m = wp.min(_edge_min(conic, lx, ly, hy, True), _edge_min(conic, hx, ly, hy, True))
    m = wp.min(m, wp.min(_edge_min(conic, ly, lx, hx, False), _edge_min(conic, hy, lx, hx, False)))
    return m <= k2


@wp.func
def tile_bounds(mean: wp.vec2, conic: wp.vec3, k2: float, width: int, height: int):
    """Inclusive tile index range ``(tx0, tx1, ty0, ty1)`` of the ellipse's bounding box,
    clipped to the image; empty (``tx0 > tx1``) when it misses every pixel centre."""
    det = conic[0] * conic[2] - conic[1] * conic[1]
    ex = wp.sqrt(k2 * conic[2] / det)  # k * sqrt(Sigma'_xx)
    ey = wp.sqrt(k2 * conic[0] / det)
    px0 = wp.max(int(wp.ceil(mean[0] - ex)), 0)
    px1 = wp.min(int(wp.floor(mean[0] + ex)), width - 1)
    py0 = wp.max(int(wp.ceil(mean[1] - ey)), 0)
    py1 = wp.min(int(wp.floor(mean[1] + ey)), height - 1)
    if px0 > px1 or py0 > py1:
        return 1, 0, 1, 0
    return px0 // TILE_SIZE, px1 // TILE_SIZE, py0 // TILE_SIZE, py1 // TILE_SIZE


@wp.func
def tile_hit(mean: wp.vec2, conic: wp.vec3, k2: float, tx: int, ty: int, width: int, height: int):
    x0 = float(tx * TILE_SIZE)
    y0 = float(ty * TILE_SIZE)
    x1 = float(wp.min(tx * TILE_SIZE + TILE_SIZE - 1, width - 1))
    y1 = float(wp.min(ty * TILE_SIZE + TILE_SIZE - 1, height - 1))
    return ellipse_reaches_rect(mean, conic, k2, x0, x1, y0, y1)


@wp.kernel
def count_tiles_kernel(
    mean2d: wp.array(dtype=wp.vec2),  # [C*N]
    conic: wp.array(dtype=wp.vec3),  # [C*N]
    opacity: wp.array(dtype=float),  # [C*N]
    visible: wp.array(dtype=wp.int32),  # [C*N]
    cameras: wp.array(dtype=Camera),  # [C]
    n_gaussians: int,
    counts: wp.array(dtype=wp.int32),  # [C*N] out: tiles touched
):
    flat = wp.tid()
    n = int(0)
    if visible[flat] != 0:
        cam = cameras[flat // n_gaussians]
        mu = mean2d[flat]
        q = conic[flat]
        k2 = support_mahalanobis2(opacity[flat])
        tx0, tx1, ty0, ty1 = tile_bounds(mu, q, k2, cam.width, cam.height)
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                if tile_hit(mu, q, k2, tx, ty, cam.width, cam.height):
                    n += 1
    counts[flat] = n


@wp.kernel
def write_tile_keys_kernel(
    mean2d: wp.array(dtype=wp.vec2),
    conic: wp.array(dtype=wp.vec3),
    opacity: wp.array(dtype=float),
    depth: wp.array(dtype=float),
    visible: wp.array(dtype=wp.int32),
    cameras: wp.array(dtype=Camera),
    n_gaussians: int,
    tiles_x: int,
    tiles_per_camera: int,
    offsets: wp.array(dtype=wp.int32),  # [C*N] inclusive prefix sum of counts
    keys: wp.array(dtype=wp.int64),  # [2*total] out
    values: wp.array(dtype=wp.int32),  # [2*total] out: flat index c*N+i
):
    flat = wp.tid()
    if visible[flat] == 0:
        return
    c = flat // n_gaussians
    cam = cameras[c]
    mu = mean2d[flat]
    q = conic[flat]
    k2 = support_mahalanobis2(opacity[flat])
    tx0, tx1, ty0, ty1 = tile_bounds(mu, q, k2, cam.width, cam.height)
    j = int(0)
    if flat > 0:
        j = offsets[flat - 1]
    dbits = wp.int64(wp.cast(depth[flat], wp.int32))
    for ty in range(ty0, ty1 + 1):
        for tx in range(tx0, tx1 + 1):
            if tile_hit(mu, q, k2, tx, ty, cam.width, cam.height):
                tile = wp.int64(c * tiles_per_camera + ty * tiles_x + tx)
                keys[j] = (tile << wp.int64(32)) | dbits
                values[j] = flat
                j += 1


@wp.kernel
def tile_ranges_kernel(
    keys: wp.array(dtype=wp.int64),  # sorted
    count: int,
    tile_start: wp.array(dtype=wp.int32),  # [C*tiles] out, zero-initialized
    tile_end: wp.array(dtype=wp.int32),  # [C*tiles] out, zero-initialized
):
    j = wp.tid()
    tile = int(keys[j] >> wp.int64(32))
    if j == 0:
        tile_start[tile] = j
    elif int(keys[j - 1] >> wp.int64(32)) != tile:
        tile_start[tile] = j
    if j == count - 1:
        tile_end[tile] = j + 1
    elif int(keys[j + 1] >> wp.int64(32)) != tile:
        tile_end[tile] = j + 1
