"""Monocular-network-like depth priors made from exact depth (``synth --depth mono``).

Two error models:

* ``smooth`` (:data:`SMOOTH`): the exact depth with blurred edges, times a smooth random scale
  field between 0.8 and 1.25 (bilinear over a 3x3 grid), plus 2 % noise. JDSA's 4x6 bilinear
  scale grids represent this error almost exactly: the JDSA unit tests use it.
* ``realistic`` (:data:`REALISTIC`, the default for new sequences): what monocular networks get
  wrong besides that field, each effect in its own term of :class:`MonoErrors`:

  - **per-object scale**: every region between depth edges (relative jump above
    ``edge_jump``) larger than ``min_object_px`` pixels is scaled by its own log-normal factor
    (``object_sigma``), as a network misjudges an object's size;
  - **depth-edge bleeding**: within ``bleed_px`` of a depth edge the nearer surface's depth
    spreads over the farther one (a min filter), as a network's blurry boundaries do;
  - **affine error in inverse depth**: ``1/d' = a/d + b`` (``a`` uniform in ``affine_scale``,
    ``b`` uniform in +-``affine_shift`` 1/m), the ambiguity of relative-depth networks;
  - **compressed far range**: beyond ``far_start`` m, ``d' = far_start + far_scale log(1 +
    (d - far_start) / far_scale)``: far geometry comes out too near.

Deterministic for the random generator passed in; the smooth model draws exactly what it
always drew, so its sequences are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PRIOR_MODELS = ("realistic", "smooth")


@dataclass(frozen=True)
class MonoErrors:
    blur_px: float = 2.0  # Gaussian blur sigma of the whole map
    field_range: tuple = (0.8, 1.25)  # smooth scale field (3x3 bilinear)
    noise: float = 0.02  # multiplicative per-pixel noise (sigma)
    object_sigma: float = 0.0  # log scale per region between depth edges
    edge_jump: float = 0.1  # relative depth jump that separates regions
    min_object_px: int = 50
    bleed_px: int = 0  # nearer depth spread over the farther side of an edge
    affine_scale: tuple = (1.0, 1.0)  # a in 1/d' = a/d + b
    affine_shift: float = 0.0  # |b| bound, 1/m
    far_start: float = float("inf")  # m: depth beyond this is compressed ...
    far_scale: float = 20.0  # ... logarithmically with this scale (m)


SMOOTH = MonoErrors()
REALISTIC = MonoErrors(object_sigma=0.08, bleed_px=3, affine_scale=(0.9, 1.1), affine_shift=0.02, far_start=15.0)


def depth_edges(depth: np.ndarray, jump: float) -> np.ndarray:
    """[H,W] bool: pixels next to a neighbour whose depth differs by more than ``jump``
    relative (or that have depth where the neighbour has none)."""
    edge = np.zeros(depth.shape, bool)
    for axis in (0, 1):
        a = np.moveaxis(depth, axis, 0)
        d0, d1 = a[:-1], a[1:]
        big = np.abs(d1 - d0) > jump * np.minimum(d0, d1)
        big |= (d0 > 0) != (d1 > 0)
        e = np.zeros(a.shape, bool)
        e[:-1] |= big
        e[1:] |= big
        edge |= np.moveaxis(e, 0, axis)
    return edge


def mono_like_depth(depth: np.ndarray, rng: np.random.Generator, errors: MonoErrors = SMOOTH) -> np.ndarray:
    """A depth map [H,W] (m, 0 = none) with a monocular network's errors (module docstring)
    made from the exact ``depth`` [H,W]."""
    import cv2

    h, w = depth.shape
    valid = depth > 0
    exact = depth.astype(np.float32)
    blurred = cv2.GaussianBlur(exact, (0, 0), errors.blur_px)
    lo, hi = errors.field_range
    coarse = np.exp(rng.uniform(np.log(lo), np.log(hi), (3, 3))).astype(np.float32)
    field = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR)
    noise = 1.0 + errors.noise * rng.standard_normal((h, w)).astype(np.float32)
    out = blurred * field * noise
    edges = depth_edges(exact, errors.edge_jump) if errors.bleed_px > 0 or errors.object_sigma > 0 else None
    if errors.bleed_px > 0:
        near = cv2.erode(np.where(valid, exact, np.inf).astype(np.float32), np.ones((2 * errors.bleed_px + 1,) * 2, np.uint8))
        band = cv2.dilate(edges.astype(np.uint8), np.ones((2 * errors.bleed_px + 1,) * 2, np.uint8)) > 0
        near = np.where(np.isfinite(near) & (near < 1e30), near, exact)  # (erode's border value is the largest float)
        out = np.where(band, near * field * noise, out)
    if errors.object_sigma > 0:
        n, labels = cv2.connectedComponents((valid & ~edges).astype(np.uint8), connectivity=4)
        scale = np.exp(errors.object_sigma * rng.standard_normal(n)).astype(np.float32)
        sizes = np.bincount(labels.ravel(), minlength=n)
        scale[(sizes < errors.min_object_px) | (np.arange(n) == 0)] = 1.0  # label 0: edges and no depth
        out = out * scale[labels]
    if errors.affine_scale != (1.0, 1.0) or errors.affine_shift > 0:
        a = rng.uniform(*errors.affine_scale)
        b = rng.uniform(-errors.affine_shift, errors.affine_shift)
        inv = a / np.maximum(out, 1e-6) + b
        out = (1.0 / np.maximum(inv, 1.0 / 1000.0)).astype(np.float32)  # a network always answers: at most 1 km
    if np.isfinite(errors.far_start):
        s, c = errors.far_start, errors.far_scale
        out = np.where(out > s, s + c * np.log1p(np.maximum(out - s, 0.0) / c), out).astype(np.float32)
    return np.where(valid, out, 0.0).astype(np.float32)
