"""Depth priors per keyframe view, behind a small interface.

A :class:`DepthPrior` gives, for a frame, one full-resolution depth map per camera
(m, camera-model depth, 0 = unknown) or ``None`` where it has nothing, and a per-pixel
confidence in [0, 1] that weights it in MCBA and JDSA. MCBA uses the
prior sampled on the reduced grid (:func:`grid_depth`) both to initialize inverse
depth and, JDSA-scaled, as a soft prior.

* :class:`SensorDepth` — the dataset's depth: exact sensor depth (RGB-D, synthetic
  ``exact``) is used as is; an inexact one (a folder whose ``metadata.yaml`` says
  ``depth: mono``, e.g. a monocular network's output) is a prior that JDSA rescales.
* :class:`StereoDepth` — sweep stereo between overlapping rig cameras: metric, inexact,
  with a per-pixel confidence; JDSA rescales it.
* :class:`NoDepth` — nothing: MCBA's depth starts from a constant and the scale comes
  from cross-view edges (known baselines).
* a monocular network (the paper's Metric3D) plugs in as another implementation
  (metric, not exact); none is bundled because nothing may download weights at run time.

:func:`choose_prior` maps ``tracking.depth`` (``auto | sensor | stereo | none``) onto these.
"""

from __future__ import annotations

import numpy as np

from ..buffer import grid_pixels


class DepthPrior:
    #: whether the prior is trusted as a soft constraint (else only an initial value)
    metric: bool = False
    #: whether it is exact up to noise (sensor depth): then JDSA must not rescale it, or
    #: the scale grids would follow MCBA's depths and free the metric scale
    exact: bool = False
    #: what a run reports as its depth source
    name: str = ""

    def __call__(self, frame, rig) -> list:
        """Per camera: depth [H,W] (m, 0 = unknown) or ``None``."""
        return self.with_confidence(frame, rig)[0]

    def with_confidence(self, frame, rig) -> tuple[list, list]:
        """Per camera: depth [H,W] and confidence [H,W] in [0,1] (or ``None`` both)."""
        depths = self(frame, rig)
        return depths, [None if d is None else (d > 0).astype(np.float32) for d in depths]


class SensorDepth(DepthPrior):
    """The sequence's own depth: exact sensor depth, or (``exact=False``) an inexact
    prior such as a monocular network's output that JDSA rescales."""

    metric = True

    def __init__(self, exact: bool = True):
        self.exact = exact
        self.name = "sensor" if exact else "sensor (inexact prior)"

    def __call__(self, frame, rig) -> list:
        return list(frame.depths)


class NoDepth(DepthPrior):
    """No depth at all: MCBA starts from a constant and the rig's baselines give the scale."""

    name = "none"

    def __call__(self, frame, rig) -> list:
        return [None] * len(rig)


class StereoDepth(DepthPrior):
    """Sweep stereo between overlapping cameras of the rig at the frame's timestamp
    (:class:`~mcgs_warp.frontend.stereo.RigStereo`): metric, inexact, confident only
    where the views overlap and have texture."""

    metric = True
    name = "stereo"

    def __init__(self, stereo):
        self.stereo = stereo

    def with_confidence(self, frame, rig) -> tuple[list, list]:
        return self.stereo.depth(frame.index, frame.images)


def choose_prior(sequence, mode: str, stereo_factory) -> DepthPrior:
    """The depth source for ``mode`` (``auto | sensor | stereo | none``, see
    ``tracking.depth``). ``auto``: the sequence's depth when every camera has it on every
    frame, else stereo when two cameras overlap, else none. ``stereo_factory()`` builds
    the :class:`RigStereo` (``None`` when no two cameras overlap)."""
    from ..errors import InputError

    has = sequence.depth_cameras()
    names = [c.name for c in sequence.rig.cameras]
    if mode == "auto" and any(has) and not all(has):
        with_depth = ", ".join(n for n, h in zip(names, has) if h)
        raise InputError(None, "--depth", f"the sequence has depth for some cameras only ({with_depth}); choose --depth sensor after adding the rest, or --depth stereo / none to ignore it")
    if mode == "sensor" or (mode == "auto" and all(has)):
        if not all(has):
            missing = ", ".join(n for n, h in zip(names, has) if not h)
            raise InputError(None, "--depth", f"sensor: the sequence has no depth for camera(s) {missing}")
        return SensorDepth(exact=sequence.depth_exact)
    if mode in ("stereo", "auto"):
        stereo = stereo_factory()
        if stereo is not None:
            return StereoDepth(stereo)
        if mode == "stereo":
            raise InputError(None, "--depth", "stereo: no two cameras of the rig overlap (see camera_overlap); use --depth none")
    return NoDepth()


def grid_depth(depths, rig, stride: int, shape) -> np.ndarray:
    """Depth maps sampled on the reduced grid: [C,h,w] (0 where unknown)."""
    out = np.zeros((len(rig),) + tuple(shape), np.float32)
    for c, (spec, d) in enumerate(zip(rig.cameras, depths)):
        if d is None:
            continue
        uv = grid_pixels(spec, stride).astype(int)
        g = d[uv[..., 1], uv[..., 0]]
        out[c, : g.shape[0], : g.shape[1]] = np.where(np.isfinite(g) & (g > 0), g, 0.0)
    return out


def upsample_inverse_depth(disp: np.ndarray, spec, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Reduced-grid inverse depth [h,w] (1/m, 0 = unknown) -> full-resolution depth [H,W] of
    camera ``spec`` (m, 0 = unknown) and its mask: bilinear in inverse depth, only where all
    four surrounding grid pixels are known. Grid pixel ``(u', v')`` sits at full-resolution
    ``(s u' + s/2, s v' + s/2)`` (see :func:`mcgs_warp.buffer.grid_pixels`); pixels beyond the
    outermost grid pixels take the edge values."""
    import cv2

    d = np.ascontiguousarray(disp, dtype=np.float32)
    o = stride // 2
    v, u = np.mgrid[0 : spec.height, 0 : spec.width].astype(np.float32)
    mu, mv = (u - o) / stride, (v - o) / stride
    up = cv2.remap(d, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    known = cv2.remap((d > 0).astype(np.float32), mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) > 0.999
    full = np.where(known, 1.0 / np.maximum(up, 1e-6), 0.0).astype(np.float32)
    return full, known


def upsample_inverse_depth_guided(disp: np.ndarray, spec, stride: int, image: np.ndarray, sigma_color: float = 0.1, radius: int = 1, sigma_space: float = 0.5, device=None) -> np.ndarray:
    """Joint bilateral upsampling (Kopf et al. 2007) of reduced-grid inverse depth [h,w]
    (1/m, 0 = unknown) to full-resolution depth [H,W] of camera ``spec`` (m, 0 = unknown),
    guided by its full-resolution ``image`` [H,W,3] in [0,1]: each pixel averages the known
    grid samples of the ``2 radius`` x ``2 radius`` cells around it, weighted by distance
    (``sigma_space`` cells) and by colour similarity to the pixel (``sigma_color``), so a
    depth edge stays where the image edge is instead of spreading over a cell as bilinear
    interpolation does. Unlike bilinear interpolation it fills a pixel as soon as one of
    those samples is known; pixels with none get 0. A Warp kernel
    (:func:`~mcgs_warp.kernels.refine.guided_upsample_kernel`) on ``device``."""
    import warp as wp

    from ..kernels.refine import guided_upsample_kernel

    device = wp.get_device(device)
    H, W = spec.height, spec.width
    image = np.asarray(image, np.float32)
    if image.shape != (H, W, 3):
        raise ValueError(f"upsample_inverse_depth_guided: image must be RGB [{H},{W},3] like camera {spec.name}, got {image.shape}")
    depth = wp.empty((H, W), dtype=float, device=device)
    wp.launch(
        guided_upsample_kernel,
        dim=(H, W),
        inputs=[wp.array(np.ascontiguousarray(disp, np.float32), dtype=float, device=device), wp.array(np.ascontiguousarray(image), dtype=wp.vec3, device=device), int(stride), int(radius), float(sigma_color), float(sigma_space)],
        outputs=[depth],
        device=device,
    )
    return depth.numpy()
