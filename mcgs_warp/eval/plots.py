"""PNG plots drawn with OpenCV (no plotting dependency): trajectory top view and curves."""

from __future__ import annotations

import numpy as np

from ..io import write_image

COLORS = {"gt": (0.1, 0.1, 0.1), "est": (0.85, 0.2, 0.1), "grid": (0.88, 0.88, 0.88)}


def _canvas(w, h):
    return np.full((h, w, 3), 255, np.uint8)  # OpenCV draws text on 8-bit images


def _to_bgr(c):
    return tuple(int(255 * v) for v in c[::-1])


def _save(path, img):
    write_image(path, img[..., ::-1].astype(np.float32) / 255.0)  # drawn in BGR


def _draw_axes(img, lo, hi, to_px, labels):
    import cv2

    h, w = img.shape[:2]
    for v in np.linspace(lo[0], hi[0], 6):
        x, _ = to_px(np.array([v, lo[1]]))
        cv2.line(img, (x, 40), (x, h - 40), _to_bgr(COLORS["grid"]), 1)
        cv2.putText(img, f"{v:.2f}", (x - 18, h - 22), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (77, 77, 77), 1)
    for v in np.linspace(lo[1], hi[1], 6):
        _, y = to_px(np.array([lo[0], v]))
        cv2.line(img, (50, y), (w - 20, y), _to_bgr(COLORS["grid"]), 1)
        cv2.putText(img, f"{v:.2f}", (4, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (77, 77, 77), 1)
    cv2.putText(img, labels[0], (w // 2 - 20, h - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    cv2.putText(img, labels[1], (4, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)


def plot_trajectory(path, est_xy: np.ndarray, gt_xy: np.ndarray | None, title: str = "", size=(640, 520)) -> None:
    """Top view (x, y) of the estimate (red) and ground truth (black), equal axis scales."""
    import cv2

    w, h = size
    img = _canvas(w, h)
    pts = est_xy if gt_xy is None else np.concatenate([est_xy, gt_xy])
    lo, hi = pts.min(0), pts.max(0)
    span = max(float((hi - lo).max()), 1e-6) * 1.1
    mid = (lo + hi) / 2
    lo, hi = mid - span / 2, mid + span / 2
    scale = min(w - 70, h - 80) / span

    def to_px(p):
        return int(50 + (p[0] - lo[0]) * scale), int(h - 40 - (p[1] - lo[1]) * scale)

    _draw_axes(img, lo, hi, to_px, ("x [m]", "y [m]"))
    for xy, key in ((gt_xy, "gt"), (est_xy, "est")):
        if xy is None or len(xy) < 2:
            continue
        poly = np.array([to_px(p) for p in xy], np.int32)
        cv2.polylines(img, [poly], False, _to_bgr(COLORS[key]), 2, cv2.LINE_AA)
    cv2.putText(img, title, (60, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    cv2.putText(img, "estimate", (w - 130, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.45, _to_bgr(COLORS["est"]), 1)
    if gt_xy is not None:
        cv2.putText(img, "ground truth", (w - 130, 42), cv2.FONT_HERSHEY_SIMPLEX, 0.45, _to_bgr(COLORS["gt"]), 1)
    _save(path, img)


def plot_curve(path, x: np.ndarray, ys: dict, xlabel: str, ylabel: str, title: str = "", size=(640, 360)) -> None:
    """Line plot of one or more series ``ys`` (name -> values) against ``x``."""
    import cv2

    w, h = size
    img = _canvas(w, h)
    allv = np.concatenate([np.asarray(v, float) for v in ys.values()]) if ys else np.zeros(1)
    finite = allv[np.isfinite(allv)]
    lo_y, hi_y = (finite.min(), finite.max()) if len(finite) else (0.0, 1.0)
    if hi_y - lo_y < 1e-9:
        hi_y = lo_y + 1.0
    lo = np.array([float(np.min(x)) if len(x) else 0.0, lo_y])
    hi = np.array([float(np.max(x)) if len(x) else 1.0, hi_y])
    hi[0] = max(hi[0], lo[0] + 1e-9)

    def to_px(p):
        return int(50 + (p[0] - lo[0]) / (hi[0] - lo[0]) * (w - 70)), int(h - 40 - (p[1] - lo[1]) / (hi[1] - lo[1]) * (h - 80))

    _draw_axes(img, lo, hi, to_px, (xlabel, ylabel))
    palette = [(0.85, 0.2, 0.1), (0.1, 0.4, 0.8), (0.2, 0.6, 0.2), (0.5, 0.2, 0.6)]
    for n, (name, v) in enumerate(ys.items()):
        v = np.asarray(v, float)
        ok = np.isfinite(v)
        if ok.sum() >= 2:
            poly = np.array([to_px(p) for p in np.stack([np.asarray(x, float)[ok], v[ok]], 1)], np.int32)
            cv2.polylines(img, [poly], False, _to_bgr(palette[n % 4]), 2, cv2.LINE_AA)
        cv2.putText(img, name, (w - 160, 24 + 18 * n), cv2.FONT_HERSHEY_SIMPLEX, 0.45, _to_bgr(palette[n % 4]), 1)
    cv2.putText(img, title, (60, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    _save(path, img)
