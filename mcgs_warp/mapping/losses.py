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
