"""Image quality measures: PSNR, and SSIM with its gradient (also the mapping loss).

SSIM uses the 3DGS window (11x11 Gaussian, sigma 1.5, zero padding; C1 = 0.01^2,
C2 = 0.03^2), computed in float32 with OpenCV filters.
"""

from __future__ import annotations

import numpy as np

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
_WINDOW = 11
_SIGMA = 1.5


def _blur(x: np.ndarray) -> np.ndarray:
    """Zero-padded 11x11 Gaussian filter per channel (self-adjoint)."""
    import cv2

    k = cv2.getGaussianKernel(_WINDOW, _SIGMA)
    return cv2.sepFilter2D(x, -1, k, k, borderType=cv2.BORDER_CONSTANT)


def ssim(x: np.ndarray, y: np.ndarray, with_grad: bool = True):
    """Mean SSIM of images ``x`` and ``y`` ([H,W,3]) and its gradient w.r.t. ``x``."""
    x = np.ascontiguousarray(x, np.float32)
    y = np.ascontiguousarray(y, np.float32)
    mx, my = _blur(x), _blur(y)
    sxx = _blur(x * x) - mx * mx
    syy = _blur(y * y) - my * my
    sxy = _blur(x * y) - mx * my
    A1, A2 = 2 * mx * my + SSIM_C1, 2 * sxy + SSIM_C2
    B1, B2 = mx * mx + my * my + SSIM_C1, sxx + syy + SSIM_C2
    S = (A1 * A2) / (B1 * B2)
    value = float(S.mean(dtype=np.float64))
    if not with_grad:
        return value, None
    g = 1.0 / S.size  # d mean / d S
    dS_dmx = 2 * my * A2 / (B1 * B2) - S * 2 * mx / B1
    dS_dsxx = -S / B2
    dS_dsxy = 2 * A1 / (B1 * B2)
    # raw moments: sxx = m_xx - mx^2, sxy = m_xy - mx my
    d_mx = g * (dS_dmx - 2 * mx * dS_dsxx - my * dS_dsxy)
    d_mxx = g * dS_dsxx
    d_mxy = g * dS_dsxy
    grad = _blur(d_mx) + 2 * x * _blur(d_mxx) + y * _blur(d_mxy)
    return value, grad


def psnr(rendered: np.ndarray, target: np.ndarray) -> float:
    mse = float(np.mean((np.clip(rendered, 0, 1) - target) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)
