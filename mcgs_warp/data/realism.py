"""What a real camera adds to a perfect synthetic render (``synth --realism camera``).

Applied per camera and frame to the clean render (RGB in [0,1]), in the order a sensor does:

1. **Motion blur**: the rig moves during the exposure (``exposure_s``). Every pixel averages the
   image along the path its scene point takes in the image from the start to the end of the
   exposure, found from the exact depth and the rig's motion (occlusions ignored): a point at
   depth ``Z`` seen by a pinhole of focal ``f`` while the camera moves sideways at ``v`` smears
   over ``f v exposure_s / Z`` px. The sky (no depth) moves with the rotation only.
2. **Vignetting**: ``1 - vignette r^2``, ``r`` the distance from the principal point over the
   half diagonal.
3. **Gain** per camera and frame (auto-exposure): ``exp(g)``, ``g`` a per-camera offset
   (``gain_sigma``) plus a random walk over frames (``gain_walk`` per frame), clipped to
   +-``3 gain_sigma``.
4. **Noise**: Gaussian with the variance of shot and read noise, ``shot I + read^2`` at signal ``I``.
5. **JPEG quantization** (8 bits, ``jpeg_quality``), as a compressed recording stores it.

Deterministic for the random generator passed in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

REALISM = ("none", "camera")


@dataclass
class CameraRealism:
    exposure_s: float = 0.008  # s: 8 cm of motion at 10 m/s
    vignette: float = 0.3  # brightness loss at the image corners
    gain_sigma: float = 0.1  # log gain: per-camera offset
    gain_walk: float = 0.03  # log gain: change per frame
    shot: float = 4e-4  # noise variance per unit signal (sigma 0.02 at full scale)
    read: float = 0.004  # noise sigma at zero signal
    jpeg_quality: int = 90
    blur_samples: int = 9  # samples along each pixel's path during the exposure


def image_motion(rays: np.ndarray, depth: np.ndarray, cam, T_c1_c0: np.ndarray) -> np.ndarray:
    """Pixel displacement [H,W,2] of every pixel's scene point when the camera moves by
    ``T_c1_c0`` (frame-0 camera coordinates -> frame-1 camera coordinates). ``rays`` [H,W,3]:
    camera-frame rays at unit model depth; ``depth`` [H,W] model depth (m), 0 = none (the
    sky: a point at infinity, moved by the rotation only); ``cam``: the camera's Warp struct
    (:func:`mcgs_warp.ba.edges.project_points`). Pixels without a ray, or whose point leaves
    the camera's domain, get 0."""
    from ..ba.edges import project_points

    H, W = depth.shape
    ok = np.isfinite(rays).all(-1)
    r = np.where(ok[..., None], rays, 0.0).astype(np.float64)
    X = r * depth[..., None]
    far = (depth <= 0) & ok
    X1 = X @ T_c1_c0[:3, :3].T + T_c1_c0[:3, 3]
    X1 = np.where(far[..., None], r @ T_c1_c0[:3, :3].T, X1)  # at infinity only the rotation moves it
    X0 = np.where(far[..., None], r, X)
    p1, ok1, _ = project_points(cam, X1)
    p0, ok0, _ = project_points(cam, X0)
    good = ok & ok1 & ok0
    return np.where(good[..., None], p1 - p0, 0.0).astype(np.float32)


def motion_blur(image: np.ndarray, displacement: np.ndarray, samples: int = 9) -> np.ndarray:
    """Average ``image`` [H,W,3] along each pixel's path ``p + s displacement``, ``s`` uniform
    in [-1/2, 1/2] (``displacement`` [H,W,2]: where the pixel's point moves over the whole
    exposure): a box blur of length ``|displacement|`` along the motion."""
    import cv2

    H, W = image.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    out = np.zeros(image.shape, np.float64)
    for s in ((np.arange(samples) + 0.5) / samples - 0.5).astype(np.float32):
        mx, my = (u + s * displacement[..., 0]).astype(np.float32), (v + s * displacement[..., 1]).astype(np.float32)
        out += cv2.remap(image.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return (out / samples).astype(np.float32)


def vignetting(cam_spec, strength: float) -> np.ndarray:
    """Brightness factor [H,W] ``1 - strength r^2``, ``r`` = distance from the principal point
    over the half diagonal (the image centre for a camera without intrinsics)."""
    H, W = cam_spec.height, cam_spec.width
    cx, cy = (cam_spec.intrinsics[2], cam_spec.intrinsics[3]) if cam_spec.intrinsics is not None else ((W - 1) / 2, (H - 1) / 2)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    r2 = ((u - cx) ** 2 + (v - cy) ** 2) / (0.25 * (W * W + H * H))
    return (1.0 - strength * r2).astype(np.float32)


def gains(n_frames: int, n_cameras: int, cfg: CameraRealism, rng: np.random.Generator) -> np.ndarray:
    """Auto-exposure gains [K,C] (linear factors): per-camera offset plus a per-frame random walk."""
    g = rng.normal(0.0, cfg.gain_sigma, n_cameras)[None] + np.cumsum(rng.normal(0.0, cfg.gain_walk, (n_frames, n_cameras)), axis=0)
    return np.exp(np.clip(g, -3 * cfg.gain_sigma, 3 * cfg.gain_sigma))


def add_noise(image: np.ndarray, cfg: CameraRealism, rng: np.random.Generator) -> np.ndarray:
    """Shot and read noise: Gaussian of variance ``shot I + read^2``, then clipped to [0, 1]."""
    sigma = np.sqrt(cfg.shot * np.clip(image, 0.0, None) + cfg.read**2)
    return np.clip(image + sigma * rng.standard_normal(image.shape).astype(np.float32), 0.0, 1.0)


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """8-bit JPEG encode and decode of an RGB image in [0,1]."""
    import cv2

    data = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(data[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise OSError("could not encode JPEG")
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0


def camera_image(clean: np.ndarray, displacement: np.ndarray, vignette: np.ndarray, gain: float, cfg: CameraRealism, rng: np.random.Generator) -> np.ndarray:
    """One camera's recorded image from its clean render [H,W,3]: blur (``displacement`` over
    the exposure, [H,W,2]), vignetting [H,W], gain, noise, JPEG."""
    img = motion_blur(clean, displacement, cfg.blur_samples) if np.abs(displacement).max() > 0.05 else clean.astype(np.float32)
    img = img * vignette[..., None] * np.float32(gain)
    return jpeg(add_noise(img, cfg, rng), cfg.jpeg_quality)
