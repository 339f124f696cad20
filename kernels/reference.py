"""Plain NumPy (float64) brute-force reference of the camera models and the renderer.

Kept beside the Warp kernels, as gsplat keeps a torch reference: tests compare the
two, and finite differences of this float64 renderer check the hand-written
adjoints. It follows the same numerics (see :mod:`projection`, :mod:`tiles`,
:mod:`blend`) but shares no code with them (only the near and far planes, from
:mod:`camera`): the EWA Jacobian here comes from central differences of
:func:`project`, every pixel looks at every Gaussian (no tiles), and everything is
float64 except the depth sort key, which is rounded to float32 as in the kernels so
that ties break the same way. Slow by design; for small scenes only.
"""

from __future__ import annotations

import numpy as np

from .camera import FAR, NEAR  # the one definition of the near and far planes (m)

COV2D_BLUR = 0.3
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1.0e-4
MAX_MAHALANOBIS2 = 9.0

_PINHOLE, _FISHEYE, _EQUI = 0, 1, 2


def _dist(cam) -> np.ndarray:
    return np.array([cam.dist[k] for k in range(5)], dtype=np.float64)


def project(cam, p: np.ndarray) -> np.ndarray:
    """Pixel coordinates of camera-frame points ``p`` [M,3] -> [M,2] (float64)."""
    p = np.asarray(p, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    if cam.model == _EQUI:
        lon = np.arctan2(x, z)
        lat = np.arctan2(y, np.hypot(x, z))
        return np.stack([cam.fx * lon + cam.cx, cam.fy * lat + cam.cy], axis=-1)
    a, b = x / z, y / z
    d = _dist(cam)
    if cam.model == _FISHEYE:
        r = np.hypot(a, b)
        th = np.arctan(r)
        t2 = th * th
        thd = th * (1 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))))
        scale = np.where(r > 1e-12, thd / np.maximum(r, 1e-300), 1.0)
        ad, bd = scale * a, scale * b
    else:
        k1, k2, p1, p2, k3 = d
        r2 = a * a + b * b
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        ad = a * radial + 2 * p1 * a * b + p2 * (r2 + 2 * a * a)
        bd = b * radial + p1 * (r2 + 2 * b * b) + 2 * p2 * a * b
    return np.stack([cam.fx * ad + cam.cx, cam.fy * bd + cam.cy], axis=-1)


def jacobian(cam, p: np.ndarray, rel_step: float = 1e-6) -> np.ndarray:
    """Central-difference Jacobian of :func:`project`: [M,3] -> [M,2,3]."""
    p = np.asarray(p, dtype=np.float64)
    h = rel_step * np.maximum(np.linalg.norm(p, axis=-1), 1e-3)
    J = np.empty(p.shape[:-1] + (2, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1.0
        step = h[..., None] * e
        J[..., :, k] = (project(cam, p + step) - project(cam, p - step)) / (2 * h[..., None])
    return J


def depth(cam, p: np.ndarray) -> np.ndarray:
    """Depth of camera-frame points: ``z``, or ray length for equirectangular."""
    p = np.asarray(p, dtype=np.float64)
    return np.linalg.norm(p, axis=-1) if cam.model == _EQUI else p[..., 2]


def in_domain(cam, p: np.ndarray, near: float = NEAR, far: float = FAR) -> np.ndarray:
    d = depth(cam, p)
    ok = (d >= near) & (d <= far)
    if cam.model == _EQUI:
        return ok & (p[..., 0] ** 2 + p[..., 2] ** 2 > 1e-8 * d * d)
    with np.errstate(divide="ignore", invalid="ignore"):
        n2 = (p[..., 0] ** 2 + p[..., 1] ** 2) / (p[..., 2] ** 2)
    return ok & (n2 <= np.float64(np.float32(cam.max_r2)))


def quat_to_rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [M,3,3] of quaternions [M,4] ``(x, y, z, w)`` (normalized here)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def project_gaussians(means, quats, log_scales, opacity_logits, cam, T_w_c, near=NEAR, far=FAR):
    """EWA projection into one camera. Returns a dict of [N] arrays:
    ``mean2d`` [N,2], ``conic`` [N,3], ``depth``, ``opacity``, ``visible`` (bool)."""
    T_c_w = np.linalg.inv(np.asarray(T_w_c, dtype=np.float64))
    W, t = T_c_w[:3, :3], T_c_w[:3, 3]
    pc = np.asarray(means, dtype=np.float64) @ W.T + t
    visible = in_domain(cam, pc, near, far)
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(opacity_logits, dtype=np.float64)))
    visible &= opacity >= ALPHA_MIN
    R = quat_to_rotation(quats)
    S = np.exp(np.asarray(log_scales, dtype=np.float64))
    Ms = R * S[:, None, :]
    cov = Ms @ np.swapaxes(Ms, 1, 2)
    safe = np.where(visible[:, None], pc, np.array([0.0, 0.0, 1.0]))
    M = jacobian(cam, safe) @ W
    S2 = M @ cov @ np.swapaxes(M, 1, 2)
    a = S2[:, 0, 0] + COV2D_BLUR
    b = S2[:, 0, 1]
    c = S2[:, 1, 1] + COV2D_BLUR
    det = a * c - b * b
    uv = project(cam, safe)
    W_, H_ = cam.width, cam.height
    visible &= (uv[:, 0] >= -W_) & (uv[:, 0] <= 2 * W_) & (uv[:, 1] >= -H_) & (uv[:, 1] <= 2 * H_)
    visible &= (det > 0) & (det < 1e30)
    det = np.where(visible, det, 1.0)
    return {
        "mean2d": uv,
        "conic": np.stack([c / det, -b / det, a / det], axis=-1),
        "depth": depth(cam, safe),
        "opacity": opacity,
        "visible": visible,
    }


def render(means, quats, log_scales, opacity_logits, colors, cam, T_w_c, near=NEAR, far=FAR, median: bool = False):
    """Brute-force render of one camera. Returns ``(color [H,W,3], depth [H,W], alpha [H,W])``,
    and with ``median`` the median depth [H,W] too (the depth of the splat at which the
    transmittance falls below 0.5; 0 where it never does)."""
    proj = project_gaussians(means, quats, log_scales, opacity_logits, cam, T_w_c, near, far)
    colors = np.asarray(colors, dtype=np.float64)
    H, W = cam.height, cam.width
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    idx = np.nonzero(proj["visible"])[0]
    order = idx[np.lexsort((idx, proj["depth"][idx].astype(np.float32)))]
    C = np.zeros((H, W, 3))
    D = np.zeros((H, W))
    T = np.ones((H, W))
    done = np.zeros((H, W), dtype=bool)
    M = np.zeros((H, W))
    for i in order:
        mu, q, o = proj["mean2d"][i], proj["conic"][i], proj["opacity"][i]
        dx, dy = xs - mu[0], ys - mu[1]
        m = q[0] * dx * dx + 2 * q[1] * dx * dy + q[2] * dy * dy
        alpha = np.minimum(ALPHA_MAX, o * np.exp(-0.5 * m))
        use = (m <= MAX_MAHALANOBIS2) & (alpha >= ALPHA_MIN) & ~done
        next_T = T * (1 - alpha)
        stop = use & (next_T < T_MIN)
        done |= stop
        use &= ~stop
        w = np.where(use, alpha * T, 0.0)
        C += w[..., None] * colors[i]
        D += w * proj["depth"][i]
        M = np.where(use & (T >= 0.5) & (next_T < 0.5), proj["depth"][i], M)
        T = np.where(use, next_T, T)
    A = 1.0 - T
    depth_img = np.where(A > 0, D / np.where(A > 0, A, 1.0), 0.0)
    return (C, depth_img, A, M) if median else (C, depth_img, A)
