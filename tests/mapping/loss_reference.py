"""NumPy reference of the mapping loss (the host version the device kernels replaced).

Per-image arrays on the host, float64: ``[H,W,3]`` colour, ``[H,W]`` depth. The
device loss (:mod:`mcgs_warp.mapping.losses`) must give the same values and gradients.
"""

from __future__ import annotations

import numpy as np

from mcgs_warp.eval.metrics import psnr, ssim


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


def depth_loss(rendered: np.ndarray, target: np.ndarray):
    """Mean ``|D - d|`` over pixels with a target depth, and its gradient w.r.t. ``D``."""
    valid = target > 0
    n = max(int(valid.sum()), 1)
    diff = np.where(valid, rendered - target, 0.0)
    return float(np.abs(diff).sum() / n), np.sign(diff) / n


def _normals(X: np.ndarray):
    """Edges ``a = X[y,x+1] - X[y,x]``, ``b = X[y+1,x] - X[y,x]`` and the unnormalized
    normals ``a x b`` [H-1,W-1,3] of a point image X [H,W,3]."""
    a = X[:-1, 1:] - X[:-1, :-1]
    b = X[1:, :-1] - X[:-1, :-1]
    return a, b, np.cross(a, b)


def normal_loss(depth: np.ndarray, target_depth: np.ndarray, rays: np.ndarray):
    """Eq. 11 normal term ``mean(1 - <n, n_prior>)`` and its gradient w.r.t. ``depth``
    (``rays`` [H,W,3]: unit-depth rays). Quads whose three depths are not all known in
    both maps, or whose normal is degenerate, do not count."""
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


def keyframe_loss(color, depth, sizes, images, depths, rays, exposure, lambda_ssim, lambda_depth, lambda_normal):
    """The mapper's former host loss of one keyframe: ``color`` [C,H,W,3] and ``depth``
    [C,H,W] padded renders, ``sizes`` [(h, w)] per camera, ``images``/``depths``/``rays``
    per camera (depth ``None`` = none), ``exposure`` [C,2] (log a, b). Returns (total,
    grad colour [C,H,W,3], grad depth [C,H,W], grad exposure [C,2], PSNR [C])."""
    color = np.asarray(color, np.float64)
    depth = np.asarray(depth, np.float64)
    gC, gD = np.zeros_like(color), np.zeros_like(depth)
    exp_grad = np.zeros((len(sizes), 2))
    total, psnrs = 0.0, []
    for c, (h, w) in enumerate(sizes):
        a, b = np.exp(exposure[c, 0]), exposure[c, 1]
        pred = a * color[c, :h, :w] + b
        lc, gc = color_loss(pred, images[c], lambda_ssim)
        total += lc
        gC[c, :h, :w] = a * gc
        exp_grad[c] = [np.sum(gc * color[c, :h, :w]) * a, np.sum(gc)]
        psnrs.append(psnr(pred, images[c]))
        d_t = depths[c]
        if d_t is not None and lambda_depth > 0:
            ld, gd = depth_loss(depth[c, :h, :w], d_t)
            total += lambda_depth * ld
            gD[c, :h, :w] = lambda_depth * gd
        if d_t is not None and lambda_normal > 0:
            ln, gn = normal_loss(depth[c, :h, :w], d_t, rays[c])
            total += lambda_normal * ln
            gD[c, :h, :w] += lambda_normal * gn
    return total, gC, gD, exp_grad, np.array(psnrs)
