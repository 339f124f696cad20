"""Figures for people: trajectory (top view, error over time) and the mapping curve.

Drawn with matplotlib, the library evo and SLAM evaluation scripts use, on its Agg
canvas directly (a ``Figure`` with a ``FigureCanvasAgg``, no pyplot): headless, and
a user's interactive backend and pyplot state are left alone. PNGs are written
through :func:`mcgs_warp.io.atomic_write`, so a plot is complete or absent.
"""

from __future__ import annotations

import io

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from ..io import atomic_write

DPI = 100
TRAJECTORY_SIZE = (1300, 560)  # pixels (width, height) of plots/trajectory.png
MAPPING_SIZE = (900, 600)  # pixels of plots/mapping.png
GT_COLOR, EST_COLOR, CMAP = "0.15", "tab:red", "viridis"


def _figure(size) -> Figure:
    fig = Figure(figsize=(size[0] / DPI, size[1] / DPI), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, path) -> None:
    """Write ``fig`` as a PNG of exactly its pixel size, atomically."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    with atomic_write(path, "wb") as f:
        f.write(buf.getvalue())


def _smooth(v: np.ndarray, n: int) -> np.ndarray:
    """Centred moving average over ``n`` samples (NaNs ignored), same length as ``v``."""
    ok = np.isfinite(v)
    k = np.ones(n)
    num = np.convolve(np.where(ok, v, 0.0), k, "same")
    den = np.convolve(ok.astype(float), k, "same")
    return np.where(den > 0, num / np.maximum(den, 1), np.nan)


def view_plane(xyz, gravity=None) -> np.ndarray:
    """[3,2] orthonormal axes of the top view of positions ``xyz`` [N,3]: the plane
    orthogonal to ``gravity`` (a world-frame direction, any length) when it is known, else
    the motion's principal plane (its two largest principal axes). The first axis is the
    one the motion spreads along most; the second completes a right-handed view looking
    against gravity (down from above), or along the least principal axis."""
    centred = np.asarray(xyz, float) - np.mean(xyz, axis=0)
    if gravity is not None and np.linalg.norm(gravity) > 0:
        up = -np.asarray(gravity, float) / np.linalg.norm(gravity)
        flat = centred - np.outer(centred @ up, up)  # the motion seen from above
        a = np.linalg.svd(flat, full_matrices=True)[2][0] if np.abs(flat).max() > 0 else np.cross(up, np.eye(3)[np.argmin(np.abs(up))])
    else:
        _, _, vt = np.linalg.svd(centred, full_matrices=True)
        a, up = vt[0], vt[2]
    a = a / np.linalg.norm(a)
    return np.stack([a, np.cross(up, a)], 1)


def trajectory_figure(est_xyz, gt_xyz=None, timestamps=None, title: str | None = None, gravity=None, ate_label: str = "ATE") -> Figure:
    """Top view of the estimate and ground truth, the estimate coloured by its position
    error (colorbar in cm), and the translation error over time beside it.

    ``est_xyz`` [N,3] are positions aligned to the ground truth, ``gt_xyz`` [N,3] the matched
    ground-truth positions (same order) or None: then only the estimate is drawn.
    ``timestamps`` [N] (seconds) label the error axis; without them it is the pose index.
    The view is :func:`view_plane` of the ground truth (else the estimate) and ``gravity``;
    ``ate_label`` names the alignment in the headline (``SE(3) ATE`` for a metric run)."""
    est = np.asarray(est_xyz, float)
    gt = None if gt_xyz is None else np.asarray(gt_xyz, float)
    plane = view_plane(est if gt is None else gt, gravity)
    origin = (est if gt is None else gt).mean(0)
    est = (est - origin) @ plane
    gt = None if gt is None else (gt - origin) @ plane
    if gt is None:
        fig = _figure((TRAJECTORY_SIZE[1] + 120, TRAJECTORY_SIZE[1]))
        ax = fig.add_subplot()
        ax.plot(est[:, 0], est[:, 1], color=EST_COLOR, lw=1.8, label="estimate")
    else:
        if gt.shape != est.shape:
            raise ValueError(f"estimate {est.shape} and ground truth {gt.shape} positions must match one to one")
        err_cm = 100.0 * np.linalg.norm(np.asarray(est_xyz, float) - np.asarray(gt_xyz, float), axis=1)  # 3D error
        fig = _figure(TRAJECTORY_SIZE)
        ax, ax_err = fig.subplots(1, 2, width_ratios=[1.1, 1])
        ax.plot(gt[:, 0], gt[:, 1], color=GT_COLOR, lw=1.2, ls="--", label="ground truth", zorder=5)  # on top: thin
        seg = np.stack([est[:-1, :2], est[1:, :2]], 1)
        lines = LineCollection(seg, cmap=CMAP, lw=2.5, zorder=3)
        lines.set_array(0.5 * (err_cm[:-1] + err_cm[1:]))
        ax.add_collection(lines)
        dots = ax.scatter(est[:, 0], est[:, 1], c=err_cm, cmap=CMAP, s=10, zorder=4, label="estimate (colour: error)")
        lines.set_norm(dots.norm)
        fig.colorbar(dots, ax=ax, label="position error [cm]", shrink=0.9)
        ate = float(np.sqrt(np.mean(err_cm**2)))
        t = np.asarray(timestamps, float) - float(timestamps[0]) if timestamps is not None else np.arange(len(est))
        ax_err.plot(t, err_cm, color=EST_COLOR, lw=1.5, label="translation error")
        ax_err.axhline(ate, color="0.4", ls=":", lw=1.2, label=f"{ate_label} (RMSE) {ate:.2f} cm")
        ax_err.set_xlabel("time [s]" if timestamps is not None else "pose")
        ax_err.set_ylabel("translation error [cm]")
        ax_err.set_ylim(bottom=0)
        ax_err.set_title("error over time")
        ax_err.grid(True, alpha=0.3)
        ax_err.legend(loc="best")
        if title is None:
            title = f"{ate_label} {ate:.2f} cm over {len(est)} poses"
    ax.plot(*est[0, :2], "o", color="0.3", ms=6, ls="none", label="start", zorder=6)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("along the motion [m]")
    ax.set_ylabel("across [m]")
    ax.set_title("top view" if gravity is not None else "top view (principal plane of the motion)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    fig.suptitle(title if title is not None else "estimated trajectory (no ground truth)")
    return fig


def plot_trajectory(path, est_xyz, gt_xyz=None, timestamps=None, title: str | None = None, gravity=None, ate_label: str = "ATE") -> Figure:
    """Draw :func:`trajectory_figure` and write it to ``path`` (PNG); returns the figure."""
    fig = trajectory_figure(est_xyz, gt_xyz, timestamps, title, gravity, ate_label)
    save_png(fig, path)
    return fig


def mapping_figure(iterations, loss, psnr, title: str = "mapping") -> Figure:
    """Loss (log scale) and PSNR per mapping iteration, in two panels sharing the x axis;
    with many steps each is drawn faintly and a moving average over them solidly."""
    it, series = np.asarray(iterations, float), (np.asarray(loss, float), np.asarray(psnr, float))
    fig = _figure(MAPPING_SIZE)
    axes = fig.subplots(2, 1, sharex=True)
    n = max(1, len(it) // 40)
    for ax, v, color, name, unit in zip(axes, series, ("tab:blue", "tab:green"), ("loss", "PSNR"), ("", " [dB]")):
        ax.plot(it, v, color=color, lw=0.8 if n > 1 else 1.8, alpha=0.35 if n > 1 else 1.0, label=f"{name} per step")
        if n > 1:
            ax.plot(it, _smooth(v, n), color=color, lw=2.0, label=f"{name}, mean of {n} steps")
        ax.set_ylabel(name + unit)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best")
    if np.all(series[0][np.isfinite(series[0])] > 0):
        axes[0].set_yscale("log")
    axes[1].set_xlabel("mapping iteration")
    fig.suptitle(title)
    return fig


def plot_mapping(path, iterations, loss, psnr, title: str = "mapping") -> Figure:
    """Draw :func:`mapping_figure` and write it to ``path`` (PNG); returns the figure."""
    fig = mapping_figure(iterations, loss, psnr, title)
    save_png(fig, path)
    return fig
