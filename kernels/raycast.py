"""Ray casting of a procedural scene: exact colour and depth for synthetic sequences.

The scene is a room (an axis-aligned box seen from inside) or, with ``open_sky``, an
open ground plane under a sky (the street), holding boxes (rotated about the world z axis)
and spheres. Surfaces are Lambertian with 3D solid
textures (value noise in a few octaves, optionally bricks or checkers), so the
brightness of a point is the same from every camera, as photometric SLAM assumes.

One thread per (camera, pixel). Colour averages ``ss x ss`` sub-pixel rays; depth is
exact for the pixel-centre ray, in the camera model's convention (``z`` for
pinhole/fisheye, ray length for equirectangular), 0 where nothing is hit (the sky, whose
colour fades from ``sky_horizon`` to ``sky_zenith`` with the ray's elevation).
"""

from __future__ import annotations

import warp as wp

from .camera import Camera, camera_unproject

wp.set_module_options({"enable_backward": False})

NO_HIT = wp.constant(1.0e30)


@wp.struct
class Scene:
    room_min: wp.vec3  # m, world
    room_max: wp.vec3
    room_materials: wp.array(dtype=wp.int32)  # [6] faces -x, +x, -y, +y, -z, +z
    box_center: wp.array(dtype=wp.vec3)  # [B]
    box_half: wp.array(dtype=wp.vec3)  # [B] half extents in the box frame
    box_rot: wp.array(dtype=wp.vec2)  # [B] (cos, sin) of the rotation about world z
    box_material: wp.array(dtype=wp.int32)  # [B]
    sphere_center: wp.array(dtype=wp.vec3)  # [S]
    sphere_radius: wp.array(dtype=float)  # [S]
    sphere_material: wp.array(dtype=wp.int32)  # [S]
    mat_base: wp.array(dtype=wp.vec3)  # [M] RGB
    mat_accent: wp.array(dtype=wp.vec3)  # [M] RGB
    mat_freq: wp.array(dtype=float)  # [M] 1/m, texture frequency
    mat_kind: wp.array(dtype=wp.int32)  # [M] 0 noise, 1 bricks, 2 checker
    light_dir: wp.vec3  # unit, towards the light
    ambient: float  # brightness = albedo x (ambient + diffuse |n . light_dir|)
    diffuse: float
    open_sky: int  # 0: the room's six walls; 1: only its floor (z = room_min z, unbounded), sky above
    sky_horizon: wp.vec3  # RGB of the sky at the horizon (open_sky)
    sky_zenith: wp.vec3  # RGB straight up


def make_scene(room_min, room_max, room_materials, boxes, spheres, materials, light_dir, ambient: float, diffuse: float, open_sky: bool = False, sky=((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), device=None) -> Scene:
    """A :class:`Scene` from host arrays: ``boxes`` = (centres [B,3], half extents [B,3],
    yaw [B] rad, material [B]), ``spheres`` = (centres [S,3], radii [S], material [S]),
    ``materials`` = (base [M,3], accent [M,3], frequency [M] 1/m, kind [M]), ``light_dir``
    [3] (normalized here), ``sky`` = (horizon, zenith) RGB for ``open_sky``."""
    import numpy as np

    def arr(a, dtype):
        return wp.array(np.ascontiguousarray(a, dtype=np.int32 if dtype is wp.int32 else np.float32), dtype=dtype, device=device)

    s = Scene()
    s.room_min, s.room_max = wp.vec3(*room_min), wp.vec3(*room_max)
    s.room_materials = arr(room_materials, wp.int32)
    centres, halves, yaw, box_mat = boxes
    s.box_center, s.box_half = arr(centres, wp.vec3), arr(halves, wp.vec3)
    s.box_rot = arr(np.stack([np.cos(yaw), np.sin(yaw)], 1).reshape(-1, 2), wp.vec2)
    s.box_material = arr(box_mat, wp.int32)
    s.sphere_center, s.sphere_radius, s.sphere_material = arr(spheres[0], wp.vec3), arr(spheres[1], float), arr(spheres[2], wp.int32)
    s.mat_base, s.mat_accent = arr(materials[0], wp.vec3), arr(materials[1], wp.vec3)
    s.mat_freq, s.mat_kind = arr(materials[2], float), arr(materials[3], wp.int32)
    light = np.asarray(light_dir, np.float64)
    s.light_dir = wp.vec3(*(light / np.linalg.norm(light)))
    s.ambient, s.diffuse = float(ambient), float(diffuse)
    s.open_sky = int(bool(open_sky))
    s.sky_horizon, s.sky_zenith = wp.vec3(*sky[0]), wp.vec3(*sky[1])
    return s


@wp.func
def _hash(ix: int, iy: int, iz: int):
    h = wp.uint32(ix) * wp.uint32(73856093) ^ wp.uint32(iy) * wp.uint32(19349663) ^ wp.uint32(iz) * wp.uint32(83492791)
    h = (h ^ (h >> wp.uint32(13))) * wp.uint32(1274126177)
    h = h ^ (h >> wp.uint32(16))
    return float(h & wp.uint32(16777215)) / 16777216.0


@wp.func
def value_noise(p: wp.vec3):
    """Smooth 3D value noise in [0, 1]."""
    fx = wp.floor(p[0])
    fy = wp.floor(p[1])
    fz = wp.floor(p[2])
    ix = int(fx)
    iy = int(fy)
    iz = int(fz)
    tx = p[0] - fx
    ty = p[1] - fy
    tz = p[2] - fz
    tx = tx * tx * (3.0 - 2.0 * tx)
    ty = ty * ty * (3.0 - 2.0 * ty)
    tz = tz * tz * (3.0 - 2.0 * tz)
    a = wp.lerp(_hash(ix, iy, iz), _hash(ix + 1, iy, iz), tx)
    b = wp.lerp(_hash(ix, iy + 1, iz), _hash(ix + 1, iy + 1, iz), tx)
    c = wp.lerp(_hash(ix, iy, iz + 1), _hash(ix + 1, iy, iz + 1), tx)
    d = wp.lerp(_hash(ix, iy + 1, iz + 1), _hash(ix + 1, iy + 1, iz + 1), tx)
    return wp.lerp(wp.lerp(a, b, ty), wp.lerp(c, d, ty), tz)


@wp.func
def albedo(scene: Scene, m: int, p: wp.vec3):
    """Surface colour of material ``m`` at world point ``p``."""
    f = scene.mat_freq[m]
    q = p * f
    n = 0.5 * value_noise(q) + 0.3 * value_noise(q * 2.7 + wp.vec3(5.1)) + 0.2 * value_noise(q * 7.3 + wp.vec3(1.7))
    t = n
    kind = scene.mat_kind[m]
    if kind == 1:  # bricks in the plane of the two largest coordinates' variation
        row = wp.floor(p[2] * 4.0)
        shift = 0.5 * (row - 2.0 * wp.floor(row * 0.5))
        u = (p[0] + p[1]) * 2.0 + shift
        mortar = wp.min(p[2] * 4.0 - row, u - wp.floor(u))
        if mortar < 0.08:
            t = 0.15 * n
        else:
            t = 0.35 + 0.65 * n
    elif kind == 2:
        s = wp.floor(p[0] * 1.5) + wp.floor(p[1] * 1.5) + wp.floor(p[2] * 1.5)
        if s - 2.0 * wp.floor(s * 0.5) > 0.5:
            t = 0.25 + 0.5 * n
        else:
            t = 0.5 + 0.5 * n
    return wp.lerp(scene.mat_accent[m], scene.mat_base[m], t)


@wp.func
def intersect_scene(scene: Scene, o: wp.vec3, d: wp.vec3):
    """Nearest hit ``(t, normal, material, point)`` of the ray ``o + t d`` (t > 0).

    On a room wall the point's coordinate across the wall is the wall's own value, not
    the rounded ``o + t d``: texture cell boundaries can lie on a wall's plane (the
    checker's at z = 0 on the floor, brick rows at z = k/4 on a brick floor or ceiling), and
    rounding (which differs between devices: CUDA fuses the multiply-add) would otherwise
    pick the cell of each sample at random."""
    best = NO_HIT
    normal = wp.vec3(0.0, 0.0, 1.0)
    mat = int(0)
    wall_axis = int(-1)  # the room wall hit, if any: its axis and coordinate
    wall_at = float(0.0)
    # Room walls, from inside: the first slab plane the ray leaves through (open sky: the floor only).
    for k in range(3):
        if scene.open_sky != 0 and (k != 2 or d[k] >= 0.0):
            continue
        if d[k] > 1.0e-12:
            t = (scene.room_max[k] - o[k]) / d[k]
            if t > 0.0 and t < best:
                best = t
                normal = wp.vec3(0.0)
                normal[k] = -1.0
                mat = scene.room_materials[2 * k + 1]
                wall_axis = k
                wall_at = scene.room_max[k]
        elif d[k] < -1.0e-12:
            t = (scene.room_min[k] - o[k]) / d[k]
            if t > 0.0 and t < best:
                best = t
                normal = wp.vec3(0.0)
                normal[k] = 1.0
                mat = scene.room_materials[2 * k]
                wall_axis = k
                wall_at = scene.room_min[k]
    for b in range(scene.box_center.shape[0]):
        # Cheap rejection by the box's bounding sphere before the slab test.
        oc = o - scene.box_center[b]
        hb = scene.box_half[b]
        bq = wp.dot(oc, d)
        dd = wp.dot(d, d)
        if bq * bq - dd * (wp.dot(oc, oc) - wp.dot(hb, hb)) < 0.0:
            continue
        cs = scene.box_rot[b]
        c = cs[0]
        s = cs[1]
        rel = o - scene.box_center[b]
        lo = wp.vec3(c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1], rel[2])  # into the box frame
        ld = wp.vec3(c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2])
        h = scene.box_half[b]
        tmin = float(-1.0e30)
        tmax = float(1.0e30)
        axis = int(0)
        sign = float(1.0)
        for k in range(3):
            if wp.abs(ld[k]) < 1.0e-12:
                if lo[k] < -h[k] or lo[k] > h[k]:
                    tmin = 1.0e30
            else:
                t1 = (-h[k] - lo[k]) / ld[k]
                t2 = (h[k] - lo[k]) / ld[k]
                sg = float(-1.0)
                if t1 > t2:
                    tmp = t1
                    t1 = t2
                    t2 = tmp
                    sg = 1.0
                if t1 > tmin:
                    tmin = t1
                    axis = k
                    sign = sg
                tmax = wp.min(tmax, t2)
        if tmin <= tmax and tmin > 0.0 and tmin < best:
            best = tmin
            nl = wp.vec3(0.0)
            nl[axis] = sign
            normal = wp.vec3(c * nl[0] - s * nl[1], s * nl[0] + c * nl[1], nl[2])
            mat = scene.box_material[b]
            wall_axis = -1
    for k in range(scene.sphere_center.shape[0]):
        oc = o - scene.sphere_center[k]
        r = scene.sphere_radius[k]
        bq = wp.dot(oc, d)
        dd = wp.dot(d, d)
        disc = bq * bq - dd * (wp.dot(oc, oc) - r * r)
        if disc > 0.0:
            t = (-bq - wp.sqrt(disc)) / dd
            if t > 0.0 and t < best:
                best = t
                normal = wp.normalize(oc + t * d)
                mat = scene.sphere_material[k]
                wall_axis = -1
    p = o + best * d
    if wall_axis >= 0:
        p[wall_axis] = wall_at
    return best, normal, mat, p


@wp.func
def shade(scene: Scene, o: wp.vec3, d: wp.vec3):
    t, n, m, p = intersect_scene(scene, o, d)
    if t >= NO_HIT:
        if scene.open_sky != 0:
            up = wp.max(d[2] / wp.length(d), 0.0)
            return wp.lerp(scene.sky_horizon, scene.sky_zenith, wp.sqrt(up)), 0.0
        return wp.vec3(0.0), 0.0
    lambert = wp.abs(wp.dot(n, scene.light_dir))
    return albedo(scene, m, p) * (scene.ambient + scene.diffuse * lambert), t


@wp.kernel
def camera_rays_kernel(
    cameras: wp.array(dtype=Camera),  # [C]
    ss: int,
    centre: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out: pixel-centre rays
    sub: wp.array(dtype=wp.vec3, ndim=3),  # [C,H*ss,W*ss] out: sub-pixel rays
):
    """Camera-frame ray directions scaled to unit model depth (same for every frame)."""
    c, y, x = wp.tid()
    cam = cameras[c]
    if x >= cam.width or y >= cam.height:
        return
    centre[c, y, x] = camera_unproject(cam, wp.vec2(float(x), float(y)), 1.0)
    for sy in range(ss):
        for sx in range(ss):
            u = float(x) + (float(sx) + 0.5) / float(ss) - 0.5
            v = float(y) + (float(sy) + 0.5) / float(ss) - 0.5
            sub[c, y * ss + sy, x * ss + sx] = camera_unproject(cam, wp.vec2(u, v), 1.0)


@wp.kernel
def raycast_kernel(
    scene: Scene,
    cameras: wp.array(dtype=Camera),  # [C]
    T_w_c: wp.array(dtype=wp.mat44),  # [C] camera -> world
    centre_rays: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] from camera_rays_kernel
    sub_rays: wp.array(dtype=wp.vec3, ndim=3),  # [C,H*ss,W*ss]
    ss: int,  # sub-pixel samples per axis for colour
    row0: int,  # first image row of this launch
    color: wp.array(dtype=wp.vec3, ndim=3),  # [C,H,W] out
    depth: wp.array(dtype=float, ndim=3),  # [C,H,W] out, m
):
    c, yb, x = wp.tid()
    y = yb + row0
    cam = cameras[c]
    if x >= cam.width or y >= cam.height:
        return
    T = T_w_c[c]
    R = wp.mat33(T[0, 0], T[0, 1], T[0, 2], T[1, 0], T[1, 1], T[1, 2], T[2, 0], T[2, 1], T[2, 2])
    o = wp.vec3(T[0, 3], T[1, 3], T[2, 3])
    # Depth: the pixel-centre ray is scaled so that t is the camera model's depth. A pixel
    # without a ray (NaN from camera_unproject: beyond a fisheye's 90 degrees) sees nothing:
    # depth 0, black.
    ray = centre_rays[c, y, x]
    d0 = float(0.0)
    if wp.isfinite(ray):
        t0, n0, m0, p0 = intersect_scene(scene, o, R * ray)
        d0 = wp.where(t0 < NO_HIT, t0, 0.0)
    depth[c, y, x] = d0
    acc = wp.vec3(0.0)
    for sy in range(ss):
        for sx in range(ss):
            sub = sub_rays[c, y * ss + sy, x * ss + sx]
            if wp.isfinite(sub):
                col, t = shade(scene, o, R * sub)
                acc += col
    color[c, y, x] = acc / float(ss * ss)
