"""Camera models as Warp functions: project, unproject, and derivatives of project.

Conventions (DESIGN.md, "Cameras"):

* Camera frame: x right, y down, z forward (OpenCV). Points are metres.
* Pixel coordinates follow OpenCV: the centre of pixel (row r, column u) is the
  continuous coordinate ``(u, r)``.
* ``pinhole``: normalized ``n = (x/z, y/z)``, OpenCV radial-tangential distortion
  ``dist = (k1, k2, p1, p2, k3)``, ``uv = (fx*n_d.x + cx, fy*n_d.y + cy)``.
* ``fisheye``: Kannala-Brandt as OpenCV's ``cv2.fisheye``:
  ``theta = atan(|n|)``, ``theta_d = theta*(1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8)``,
  ``n_d = theta_d / |n| * n``; ``dist = (k1, k2, k3, k4, 0)``. Like OpenCV it needs
  ``z > 0`` (field of view below 180 degrees).
* ``equirectangular`` (ODGS): ``lon = atan2(x, z)``, ``lat = atan2(y, sqrt(x^2+z^2))``,
  ``uv = (fx*lon + cx, fy*lat + cy)`` with ``fx = W/(2 pi)``, ``fy = H/pi``,
  ``cx = (W-1)/2``, ``cy = (H-1)/2`` (see :func:`equirectangular_intrinsics`), so the
  image spans longitudes [-pi, pi) and latitudes [-pi/2, pi/2] (y down).
* Depth: ``z`` for pinhole and fisheye, ray length ``|p|`` for equirectangular.

Besides ``project`` and its 2x3 Jacobian (used by EWA splatting and by bundle
adjustment) each model provides ``camera_jacobian_vjp``: the gradient of
``<G, J(p)>`` w.r.t. ``p`` (a Hessian-vector product), which the splatting
backward pass needs to carry gradients of the 2D covariance into the 3D mean.
``numpy`` twins of every function live in :mod:`reference` for tests.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

PINHOLE = wp.constant(0)
FISHEYE = wp.constant(1)
EQUIRECTANGULAR = wp.constant(2)

#: Model name -> integer id stored in :class:`Camera`.
MODEL_IDS = {"pinhole": 0, "fisheye": 1, "equirectangular": 2}
#: Near and far planes (m, DESIGN.md), along the model's depth (``camera_depth``): the
#: renderer culls Gaussians outside them and MCBA drops residuals whose point lies outside.
#: The one definition; the other modules import these.
NEAR = wp.constant(0.01)
FAR = wp.constant(100.0)
#: Squared pixel error (px^2) up to which :func:`camera_unproject` accepts its Newton
#: solution; a pixel it cannot reproduce that closely has no ray.
UNPROJECT_TOL_PX2 = wp.constant(1.0e-4)
#: Number of distortion coefficients each model takes.
N_DIST = {"pinhole": 5, "fisheye": 4, "equirectangular": 0}

vec5 = wp.types.vector(5, dtype=wp.float32)
mat23 = wp.types.matrix(shape=(2, 3), dtype=wp.float32)


@wp.struct
class Camera:
    """Intrinsics of one camera (a rig holds several)."""

    model: wp.int32  # PINHOLE, FISHEYE or EQUIRECTANGULAR
    width: wp.int32  # pixels
    height: wp.int32  # pixels
    fx: wp.float32  # pixels
    fy: wp.float32
    cx: wp.float32
    cy: wp.float32
    dist: vec5  # radtan (k1 k2 p1 p2 k3) or fisheye (k1 k2 k3 k4 0)
    max_r2: wp.float32  # largest |n|^2 where the distortion is monotonic; beyond it points are invalid


# --------------------------------------------------------------------------------------
# Distortion maps on normalized coordinates n = (x/z, y/z): value, Jacobian, and the
# derivatives of the Jacobian w.r.t. n.x and n.y.


@wp.func
def radtan_distort(n: wp.vec2, d: vec5):
    """OpenCV radial-tangential distortion of normalized ``n``.

    Returns ``(n_d, J, dJ/dn.x, dJ/dn.y)`` with ``J = d n_d / d n`` (2x2)."""
    k1 = d[0]
    k2 = d[1]
    p1 = d[2]
    p2 = d[3]
    k3 = d[4]
    a = n[0]
    b = n[1]
    r2 = a * a + b * b
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    r1 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    rr2 = 2.0 * k2 + 6.0 * k3 * r2  # d^2 radial / d r2^2
    nd = wp.vec2(
        a * radial + 2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a),
        b * radial + p1 * (r2 + 2.0 * b * b) + 2.0 * p2 * a * b,
    )
    off = 2.0 * a * b * r1 + 2.0 * p1 * a + 2.0 * p2 * b
    J = wp.mat22(
        radial + 2.0 * a * a * r1 + 2.0 * p1 * b + 6.0 * p2 * a,
        off,
        off,
        radial + 2.0 * b * b * r1 + 6.0 * p1 * b + 2.0 * p2 * a,
    )
    e_ab = 2.0 * b * r1 + 4.0 * a * a * b * rr2 + 2.0 * p1
    e_ba = 2.0 * a * r1 + 4.0 * a * b * b * rr2 + 2.0 * p2
    dJa = wp.mat22(6.0 * a * r1 + 4.0 * a * a * a * rr2 + 6.0 * p2, e_ab, e_ab, e_ba)
    dJb = wp.mat22(e_ab, e_ba, e_ba, 6.0 * b * r1 + 4.0 * b * b * b * rr2 + 6.0 * p1)
    return nd, J, dJa, dJb


@wp.func
def fisheye_distort(n: wp.vec2, d: vec5):
    """Kannala-Brandt (OpenCV fisheye) distortion of normalized ``n``.

    Written as ``n_d = f(r) n`` with ``r = |n|``, so ``J = f I + g n n^T`` with
    ``g = f'/r`` and ``dJ/dn_k = g n_k I + h n_k n n^T + g (e_k n^T + n e_k^T)``,
    ``h = g'/r``. Near the axis a series in ``r`` avoids the 0/0 forms."""
    k1 = d[0]
    k2 = d[1]
    k3 = d[2]
    k4 = d[3]
    r2 = wp.dot(n, n)
    r = wp.sqrt(r2)
    f = float(0.0)
    g = float(0.0)
    h = float(0.0)
    if r < 0.05:
        c = k1 - 1.0 / 3.0
        e = 0.2 - k1 + k2
        f = 1.0 + r2 * (c + e * r2)
        g = 2.0 * c + 4.0 * e * r2
        h = 8.0 * e
    else:
        th = wp.atan(r)
        t2 = th * th
        s = 1.0 + r2
        th1 = 1.0 / s
        th2 = -2.0 * r / (s * s)
        p0 = th * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        p1 = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        p2 = th * (6.0 * k1 + t2 * (20.0 * k2 + t2 * (42.0 * k3 + t2 * 72.0 * k4)))
        td1 = p1 * th1
        td2 = p2 * th1 * th1 + p1 * th2
        f = p0 / r
        f1 = (td1 - f) / r
        f2 = (td2 - 2.0 * f1) / r
        g = f1 / r
        h = (f2 - g) / r2
    a = n[0]
    b = n[1]
    nd = f * n
    J = wp.mat22(f + g * a * a, g * a * b, g * a * b, f + g * b * b)
    # dJ/da = g a I + h a n n^T + g (e_a n^T + n e_a^T)
    dJa = wp.mat22(
        g * a + h * a * a * a + 2.0 * g * a,
        h * a * a * b + g * b,
        h * a * a * b + g * b,
        g * a + h * a * b * b,
    )
    dJb = wp.mat22(
        g * b + h * b * a * a,
        h * a * b * b + g * a,
        h * a * b * b + g * a,
        g * b + h * b * b * b + 2.0 * g * b,
    )
    return nd, J, dJa, dJb


@wp.func
def distort(cam: Camera, n: wp.vec2):
    """Distortion of the camera's model (pinhole or fisheye) with its derivatives."""
    if cam.model == FISHEYE:
        return fisheye_distort(n, cam.dist)
    return radtan_distort(n, cam.dist)


# --------------------------------------------------------------------------------------
# Equirectangular helpers: gradients and Hessians of longitude and latitude.


@wp.func
def _lonlat_grad(p: wp.vec3):
    x = p[0]
    y = p[1]
    z = p[2]
    q = x * x + z * z
    rho = wp.sqrt(q)
    s = q + y * y
    glon = wp.vec3(z / q, 0.0, -x / q)
    glat = wp.vec3(-x * y / (s * rho), rho / s, -z * y / (s * rho))
    return glon, glat


@wp.func
def _lonlat_hessian(p: wp.vec3):
    x = p[0]
    y = p[1]
    z = p[2]
    q = x * x + z * z
    rho = wp.sqrt(q)
    s = q + y * y
    q2 = q * q
    hlon = wp.mat33(
        -2.0 * x * z / q2, 0.0, (x * x - z * z) / q2,
        0.0, 0.0, 0.0,
        (x * x - z * z) / q2, 0.0, 2.0 * x * z / q2,
    )  # fmt: skip
    s2r = s * s * rho
    sr3 = s * rho * q
    lxx = -y * (1.0 / (s * rho) - 2.0 * x * x / s2r - x * x / sr3)
    lzz = -y * (1.0 / (s * rho) - 2.0 * z * z / s2r - z * z / sr3)
    lxz = x * y * z * (2.0 / s2r + 1.0 / sr3)
    lxy = x * (y * y - q) / s2r
    lzy = z * (y * y - q) / s2r
    lyy = -2.0 * y * rho / (s * s)
    hlat = wp.mat33(lxx, lxy, lxz, lxy, lyy, lzy, lxz, lzy, lzz)
    return hlon, hlat


# --------------------------------------------------------------------------------------
# Public camera functions (dispatch on cam.model).


@wp.func
def camera_project(cam: Camera, p: wp.vec3):
    """Pixel coordinates ``(u, v)`` of camera-frame point ``p`` (metres)."""
    if cam.model == EQUIRECTANGULAR:
        lon = wp.atan2(p[0], p[2])
        lat = wp.atan2(p[1], wp.sqrt(p[0] * p[0] + p[2] * p[2]))
        return wp.vec2(cam.fx * lon + cam.cx, cam.fy * lat + cam.cy)
    n = wp.vec2(p[0] / p[2], p[1] / p[2])
    nd, J, dJa, dJb = distort(cam, n)
    return wp.vec2(cam.fx * nd[0] + cam.cx, cam.fy * nd[1] + cam.cy)


@wp.func
def camera_jacobian(cam: Camera, p: wp.vec3):
    """2x3 Jacobian ``d(u, v) / d p`` of :func:`camera_project` (pixels per metre)."""
    if cam.model == EQUIRECTANGULAR:
        glon, glat = _lonlat_grad(p)
        return mat23(
            cam.fx * glon[0], cam.fx * glon[1], cam.fx * glon[2],
            cam.fy * glat[0], cam.fy * glat[1], cam.fy * glat[2],
        )  # fmt: skip
    iz = 1.0 / p[2]
    n = wp.vec2(p[0] * iz, p[1] * iz)
    nd, J, dJa, dJb = distort(cam, n)
    jn = mat23(iz, 0.0, -n[0] * iz, 0.0, iz, -n[1] * iz)
    k = wp.mat22(cam.fx, 0.0, 0.0, cam.fy)
    return (k * J) * jn


@wp.func
def camera_jacobian_vjp(cam: Camera, p: wp.vec3, G: mat23):
    """Gradient w.r.t. ``p`` of the scalar ``sum(G * camera_jacobian(cam, p))``."""
    if cam.model == EQUIRECTANGULAR:
        hlon, hlat = _lonlat_hessian(p)
        g0 = wp.vec3(G[0, 0], G[0, 1], G[0, 2])
        g1 = wp.vec3(G[1, 0], G[1, 1], G[1, 2])
        return cam.fx * (hlon * g0) + cam.fy * (hlat * g1)
    x = p[0]
    y = p[1]
    iz = 1.0 / p[2]
    n = wp.vec2(x * iz, y * iz)
    nd, J, dJa, dJb = distort(cam, n)
    jn = mat23(iz, 0.0, -n[0] * iz, 0.0, iz, -n[1] * iz)
    # H = K G; s(p) = <H, J_D(n(p)) J_N(p)>
    H = mat23(
        cam.fx * G[0, 0], cam.fx * G[0, 1], cam.fx * G[0, 2],
        cam.fy * G[1, 0], cam.fy * G[1, 1], cam.fy * G[1, 2],
    )  # fmt: skip
    P = H * wp.transpose(jn)  # 2x2
    ds_dn = wp.vec2(wp.ddot(P, dJa), wp.ddot(P, dJb))
    grad = wp.transpose(jn) * ds_dn
    M = wp.transpose(J) * H  # 2x3
    iz2 = iz * iz
    grad += wp.vec3(
        -M[0, 2] * iz2,
        -M[1, 2] * iz2,
        -(M[0, 0] + M[1, 1]) * iz2 + 2.0 * (M[0, 2] * x + M[1, 2] * y) * iz2 * iz,
    )
    return grad


@wp.func
def camera_depth(cam: Camera, p: wp.vec3):
    """Depth of camera-frame ``p``: ``z`` (pinhole, fisheye) or ray length (equirectangular)."""
    if cam.model == EQUIRECTANGULAR:
        return wp.length(p)
    return p[2]


@wp.func
def camera_depth_grad(cam: Camera, p: wp.vec3):
    """Gradient of :func:`camera_depth` w.r.t. ``p``."""
    if cam.model == EQUIRECTANGULAR:
        return p / wp.length(p)
    return wp.vec3(0.0, 0.0, 1.0)


@wp.func
def camera_in_domain(cam: Camera, p: wp.vec3, near: float, far: float):
    """True where ``p`` lies between the near and far planes and inside the model's
    valid domain (monotonic distortion; away from the equirectangular poles)."""
    d = camera_depth(cam, p)
    if d < near or d > far:
        return False
    if cam.model == EQUIRECTANGULAR:
        return p[0] * p[0] + p[2] * p[2] > 1.0e-8 * d * d
    n2 = (p[0] * p[0] + p[1] * p[1]) / (p[2] * p[2])
    return n2 <= cam.max_r2


@wp.func
def camera_unproject(cam: Camera, uv: wp.vec2, depth: float):
    """Camera-frame point seen at pixel ``uv`` with depth ``depth`` (same meaning as
    :func:`camera_depth`). Distortion is inverted by Newton iterations.

    NaN (all three coordinates) where the pixel has no ray in the model's domain: a
    fisheye pixel beyond 90 degrees off the axis, a pinhole pixel only reached past the
    distortion's fold (``|n|^2 > max_r2``), or wherever Newton does not reproduce the
    pixel to 0.01 px. NaN fails every domain and depth test (:func:`camera_in_domain`
    returns False for it), so such pixels drop out of matching and BA; consumers that do
    not test the domain must skip non-finite rays themselves."""
    if cam.model == EQUIRECTANGULAR:
        lon = (uv[0] - cam.cx) / cam.fx
        lat = (uv[1] - cam.cy) / cam.fy
        cl = wp.cos(lat)
        return depth * wp.vec3(cl * wp.sin(lon), wp.sin(lat), cl * wp.cos(lon))
    m = wp.vec2((uv[0] - cam.cx) / cam.fx, (uv[1] - cam.cy) / cam.fy)
    n = m
    for _ in range(20):
        nd, J, dJa, dJb = distort(cam, n)
        n = n - wp.inverse(J) * (nd - m)
    nd, J, dJa, dJb = distort(cam, n)
    ex = (nd[0] - m[0]) * cam.fx
    ey = (nd[1] - m[1]) * cam.fy
    # Written so that NaN fails it: a diverged Newton run gives inf or NaN here.
    if wp.dot(n, n) <= cam.max_r2 and ex * ex + ey * ey <= UNPROJECT_TOL_PX2:
        return depth * wp.vec3(n[0], n[1], 1.0)
    return wp.vec3(wp.nan, wp.nan, wp.nan)


# --------------------------------------------------------------------------------------
# Host helpers.


def equirectangular_intrinsics(width: int, height: int) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` of a full-sphere equirectangular image of this size."""
    return width / (2.0 * math.pi), height / math.pi, (width - 1) / 2.0, (height - 1) / 2.0


def monotonic_radius2(model: str, dist) -> float:
    """Largest squared normalized radius ``|n|^2`` up to which the radial distortion
    increases monotonically (beyond it distant points would fold back into the image)."""
    d = list(dist) + [0.0] * (5 - len(dist))
    if model == "pinhole":
        r = np.linspace(0.0, 20.0, 200001)
        r2 = r * r
        rd = r * (1 + r2 * (d[0] + r2 * (d[1] + r2 * d[4])))
    elif model == "fisheye":
        th = np.linspace(0.0, math.pi / 2 - 1e-4, 200001)
        t2 = th * th
        rd = th * (1 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))))
        r = np.tan(th)
    else:
        return float("inf")
    bad = np.nonzero(np.diff(rd) <= 0)[0]
    rmax = r[bad[0]] if len(bad) else r[-1]
    return float(min(rmax * rmax, 3.0e38))


def make_camera(
    model: str,
    width: int,
    height: int,
    intrinsics=None,
    dist=(),
) -> Camera:
    """Build a :class:`Camera` struct, validating the arguments.

    ``intrinsics`` is ``(fx, fy, cx, cy)`` in pixels; for ``equirectangular`` it may be
    ``None`` (full sphere, :func:`equirectangular_intrinsics`). ``dist`` has 5
    coefficients for ``pinhole`` (k1 k2 p1 p2 k3, or fewer: the rest are 0), 4 for
    ``fisheye`` (k1..k4) and none for ``equirectangular``."""
    if model not in MODEL_IDS:
        raise ValueError(f"camera model: expected one of {sorted(MODEL_IDS)}, got {model!r}")
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"camera resolution: expected positive width and height, got {width}x{height}")
    if intrinsics is None:
        if model != "equirectangular":
            raise ValueError(f"camera intrinsics: expected (fx, fy, cx, cy) for model {model!r}")
        intrinsics = equirectangular_intrinsics(width, height)
    intr = [float(v) for v in intrinsics]
    if len(intr) != 4 or not all(math.isfinite(v) for v in intr) or intr[0] <= 0 or intr[1] <= 0:
        raise ValueError(f"camera intrinsics: expected 4 finite numbers (fx, fy > 0), got {list(intrinsics)}")
    dist = [float(v) for v in dist]
    if len(dist) > N_DIST[model] or not all(math.isfinite(v) for v in dist):
        raise ValueError(
            f"camera distortion: expected at most {N_DIST[model]} finite numbers for {model!r}, got {dist}"
        )
    cam = Camera()
    cam.model = MODEL_IDS[model]
    cam.width = int(width)
    cam.height = int(height)
    cam.fx, cam.fy, cam.cx, cam.cy = intr
    cam.dist = vec5(*(dist + [0.0] * (5 - len(dist))))
    cam.max_r2 = monotonic_radius2(model, dist)
    return cam
