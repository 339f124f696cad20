"""Sky segmentation of a keyframe view, so that the background (not Gaussians) renders the sky.

Outdoor rigs see a bright, smooth sky that nothing can put at a depth: stereo and flow find
no texture there, and the few depths they do report are spurious (far, scattered). A
Gaussian seeded at such a depth, or densified into the sky from a tree top, is a grey blob
that the views from other positions disagree with. As outdoor splatting systems do with a
sky mask, a pixel is *sky* when all of these hold:

- **flat**: the local standard deviation of its luminance over a ``window`` px box is below
  ``flatness`` (sky, even cloudy, varies slowly; foliage and façades do not);
- **bright**: its luminance is at least ``brightness`` times the image's 99th percentile
  (the sky is the light source of a daylight scene, so it is near the image's brightest);
- **large and unmeasured**: it lies in a connected region of such pixels that covers at
  least ``min_area`` of the image (a white road sign is not sky) and of which at most
  ``max_measured`` have a mapping depth target nearer than ``far`` (m): a lit wall has
  depth; the sky has none, apart from the spurious matches that stereo and flow report
  in any uniform region (which is why a single pixel's depth does not decide).

The mask is then grown by ``margin`` px, so tree-top Gaussians are kept out of the sky's
edge too. Indoors nothing qualifies (walls have depth, ceilings are not the brightest
large flat region without one) and the mask is empty. The mapper neither seeds nor keeps
Gaussians there: sky pixels get no depth target and a loss on the rendered alpha
(:class:`~mcgs_warp.mapping.mapper.Mapper`), so the background shows through.
"""

from __future__ import annotations

import numpy as np

FAR = 100.0  # m: a depth target beyond this counts as none (the mapper passes its insert_max_depth)


def sky_mask(image: np.ndarray, depth: np.ndarray | None, far: float = FAR, window: int = 7, flatness: float = 0.02,
             brightness: float = 0.6, min_area: float = 0.01, max_measured: float = 0.5, margin: int = 2) -> np.ndarray:
    """[H,W] bool: the sky pixels of one view (module docstring). ``image`` [H,W,3] RGB in
    [0,1]; ``depth`` [H,W] m (0 = none) or None."""
    import cv2

    lum = np.ascontiguousarray(np.asarray(image, np.float32).mean(axis=2))
    h, w = lum.shape
    mean = cv2.blur(lum, (window, window), borderType=cv2.BORDER_REFLECT)
    var = cv2.blur(lum * lum, (window, window), borderType=cv2.BORDER_REFLECT) - mean * mean
    flat = np.sqrt(np.maximum(var, 0.0)) < flatness
    bright = lum >= brightness * float(np.percentile(lum, 99))
    cand = flat & bright
    if not cand.any():
        return cand
    n, labels, stats, _ = cv2.connectedComponentsWithStats(cand.astype(np.uint8), connectivity=8)
    area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
    sky = area >= min_area * h * w
    unmeasured = np.ones((h, w), bool)
    if depth is not None:
        d = np.asarray(depth)
        unmeasured = (d <= 0) | (d > far) | ~np.isfinite(d)
        measured = np.bincount(labels[~unmeasured], minlength=n)
        sky &= measured <= max_measured * area
    sky[0] = False  # label 0: not a candidate
    mask = sky[labels]
    if margin > 0 and mask.any():
        # grow into the unmeasured pixels around it (the sky's edge against tree tops)
        mask = (cv2.dilate(mask.astype(np.uint8), np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)) > 0) & (mask | unmeasured)
    return mask
