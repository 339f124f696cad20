"""Image losses of the mapping objective (paper eq. 11, with the 3DGS colour term) and
their gradients w.r.t. the rendered images.

Colour: ``(1 - l_ssim) * L1 + l_ssim * (1 - SSIM)`` (SSIM and its gradient from
:mod:`mcgs_warp.eval.metrics`). Depth: L1 where the target depth is known.
Per-image arrays on the host ([H,W,3] / [H,W]);
the Gaussian-space scale regularizer lives in :mod:`mcgs_warp.kernels.mapping`.
"""

from __future__ import annotations

import numpy as np

from ..eval.metrics import psnr, ssim  # noqa: F401  (re-exported for the mapper)

def color_loss(rendered: np.ndarray, target: np.ndarray, lambda_ssim: float = 0.2):
    """``(1 - l) * mean|x - y| + l * (1 - SSIM)`` and its gradient w.r.t. ``rendered``."""
    diff = rendered - target
    l1 = float(np.abs(diff).mean())
    g = (1 - lambda_ssim) * np.sign(diff) / diff.size
    value = (1 - lambda_ssim) * l1
    if lambda_ssim > 0:
        s, gs = ssim(rendered, target)
        value += lambda_ssim * (1 - s)
        g = g - lambda_ssim * gs
    return value, g


def depth_loss(rendered: np.ndarray, target: np.ndarray, alpha: np.ndarray | None = None):
    """Mean ``|D - d|`` over pixels with a target depth, and its gradient w.r.t. ``D``."""
    valid = target > 0
    n = max(int(valid.sum()), 1)
    diff = np.where(valid, rendered - target, 0.0)
    return float(np.abs(diff).sum() / n), np.sign(diff) / n


def _normals(X: np.ndarray):
    """Unnormalized normals [H-1,W-1,3] ``a x b`` of a point image X [H,W,3] from forward
    differences ``a = X[y,x+1] - X[y,x]``, ``b = X[y+1,x] - X[y,x]``."""
    a = X[:-1, 1:] - X[:-1, :-1]
    b = X[1:, :-1] - X[:-1, :-1]
    return a, b, np.cross(a, b)


def normal_loss(depth: np.ndarray, target_depth: np.ndarray, rays: np.ndarray):
    """Eq. 11 normal term ``mean(1 - <n, n_prior>)`` and its gradient w.r.t. ``depth``.

    Normals come from back-projected depth (``rays`` [H,W,3]: unit-depth rays) by
    forward differences, for the rendered depth and for the target depth (standing in
    for the paper's monocular normal prior). Pixels whose three depths are not all
    known in both maps do not count."""
    H, W = depth.shape
    D = np.asarray(depth, np.float64)
    Dt = np.asarray(target_depth, np.float64)
    ok = (D > 0) & (Dt > 0)
    valid = ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1]
    _, _, nt = _normals(rays * Dt[..., None])
    nt_len = np.linalg.norm(nt, axis=-1)
    a, b, n = _normals(rays * D[..., None])
    n_len = np.linalg.norm(n, axis=-1)
    valid &= (nt_len > 1e-12) & (n_len > 1e-12)
    count = max(int(valid.sum()), 1)
    nt_hat = np.where(valid[..., None], nt / np.maximum(nt_len, 1e-12)[..., None], 0.0)
    n_hat = np.where(valid[..., None], n / np.maximum(n_len, 1e-12)[..., None], 0.0)
    value = float(np.sum(valid * (1.0 - np.sum(n_hat * nt_hat, -1))) / count)
    g_hat = -nt_hat / count  # dL / d n_hat
    g_n = (g_hat - n_hat * np.sum(n_hat * g_hat, -1, keepdims=True)) / np.maximum(n_len, 1e-12)[..., None]
    g_n = np.where(valid[..., None], g_n, 0.0)
    g_a = np.cross(b, g_n)  # d(a x b)/da^T g = b x g
    g_b = np.cross(g_n, a)  # d(a x b)/db^T g = g x a
    gX = np.zeros((H, W, 3))
    gX[:-1, 1:] += g_a
    gX[1:, :-1] += g_b
    gX[:-1, :-1] -= g_a + g_b
    return value, np.sum(gX * rays, -1)
