"""Loop closure: revisit candidates from the poses, confirmed or rejected with the images.

:func:`loop_candidates` proposes view pairs far apart in time whose poses say they see the
same place; :func:`confirm_loops` measures both directions with a flow provider and accepts a
pair only when the matches are confident, near the prediction (the drift a loop may correct)
and agree with each other (the round trip i -> j -> i returns to its start).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..buffer import KeyframeBuffer
from .edges import LOOP, GraphConfig, _as_edges, optical_axes, reproject, view_overlap


def loop_candidates(buffer: KeyframeBuffer, keyframes=None, config: GraphConfig | None = None, exclude=(), poses=None) -> np.ndarray:
    """Revisit candidates [M,5] ``(i, ci, j, cj, LOOP)``, one direction (i later than j).

    Keyframe pairs more than ``config.loop_min_gap`` apart in the list ``keyframes`` (default:
    all) whose rig positions lie within ``config.loop_radius`` times the median spacing of
    consecutive keyframes; per camera pair, optical axes within ``config.loop_max_angle``
    degrees and reprojected overlap (current poses and depths) of at least
    ``config.loop_min_overlap`` both ways; at most ``config.loop_max_per_view`` partners per
    view of i (largest overlap first). Edges in ``exclude`` (keys ``(i, ci, j, cj)``) are skipped.
    Pose proximity only proposes: :func:`confirm_loops` decides with the images."""
    cfg = config or GraphConfig()
    T_w_b = buffer.get_poses() if poses is None else np.asarray(poses)
    kfs = np.array(list(range(len(T_w_b))) if keyframes is None else [int(k) for k in keyframes], dtype=np.int64)
    if len(kfs) < cfg.loop_min_gap + 2:
        return np.zeros((0, 5), np.int32)
    pos = T_w_b[kfs, :3, 3]
    spacing = float(np.median(np.linalg.norm(np.diff(pos, axis=0), axis=1)))
    radius = cfg.loop_radius * max(spacing, 1e-6)
    ai, aj = np.nonzero(np.linalg.norm(pos[:, None] - pos[None], axis=-1) < radius)
    keep = ai - aj > cfg.loop_min_gap
    ai, aj = ai[keep], aj[keep]
    if not len(ai):
        return np.zeros((0, 5), np.int32)
    axes = optical_axes(buffer, T_w_b)
    C = len(buffer.rig)
    cos_max = np.cos(np.radians(cfg.loop_max_angle))
    exclude = {tuple(int(v) for v in k[:4]) for k in exclude}
    cand = [
        (int(kfs[a]), ci, int(kfs[b]), cj)
        for a, b in zip(ai, aj)
        for ci in range(C)
        for cj in range(C)
        if axes[kfs[a], ci] @ axes[kfs[b], cj] >= cos_max and (int(kfs[a]), ci, int(kfs[b]), cj) not in exclude
    ]
    if not cand:
        return np.zeros((0, 5), np.int32)
    cand = np.array(cand, dtype=np.int64)
    ov, _ = view_overlap(buffer, np.concatenate([cand, cand[:, [2, 3, 0, 1]]]), poses=T_w_b, sample=cfg.sample)
    score = np.minimum(ov[: len(cand)], ov[len(cand) :])
    out, count = [], {}
    for n in np.argsort(-score, kind="stable"):
        key = (int(cand[n, 0]), int(cand[n, 1]))
        if score[n] < cfg.loop_min_overlap or count.get(key, 0) >= cfg.loop_max_per_view:
            continue
        count[key] = count.get(key, 0) + 1
        out.append((*cand[n], LOOP))
    return np.array(out, dtype=np.int32).reshape(-1, 5)


@dataclass
class LoopCheck:
    """The verdict on one loop candidate (both directions measured)."""

    edge: tuple  # (i, ci, j, cj)
    confident: float  # min over the two directions: fraction of predicted-visible pixels with weight >= 0.5
    residual_px: float  # max over the two directions: median |target - predicted|, full-resolution px
    cycle_px: float  # median round-trip error i -> j -> i through both directions' targets, full-res px
    accepted: bool


def _bilinear(field: np.ndarray, mask: np.ndarray, q: np.ndarray):
    """Sample ``field`` [h,w,k] at points ``q`` [N,2] (x, y); ``ok`` [N] where all four
    neighbours lie inside and are set in ``mask`` [h,w]."""
    h, w = mask.shape
    x0 = np.floor(q[:, 0]).astype(np.int64)
    y0 = np.floor(q[:, 1]).astype(np.int64)
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    x0, y0 = np.where(ok, x0, 0), np.where(ok, y0, 0)
    fx, fy = (q[:, 0] - x0)[:, None], (q[:, 1] - y0)[:, None]
    ok &= mask[y0, x0] & mask[y0, x0 + 1] & mask[y0 + 1, x0] & mask[y0 + 1, x0 + 1]
    val = field[y0, x0] * (1 - fx) * (1 - fy) + field[y0, x0 + 1] * fx * (1 - fy) + field[y0 + 1, x0] * (1 - fx) * fy + field[y0 + 1, x0 + 1] * fx * fy
    return val, ok


def confirm_loops(buffer: KeyframeBuffer, candidates: np.ndarray, provider, config: GraphConfig | None = None):
    """Check loop candidates [M,>=4] against the images; returns ``(edges [A,5], targets
    [A,h,w,2], weights [A,h,w], checks list[LoopCheck])`` with the accepted edges in both
    directions (kind LOOP).

    ``provider.correspondences(buffer, edges)`` (best :class:`GuidedDIS`: flow from the
    predicted reprojection) measures both directions; a provider with a ``photometric``
    method (GuidedDIS) is asked without it, and its factor is applied to the accepted edges. A candidate is accepted when, in both
    directions, at least ``config.loop_min_confident`` of the pixels predicted to be visible
    carry a confident match (weight >= 0.5); the median distance between the matches and the
    prediction stays below ``config.loop_max_residual_px`` (the drift the loop may correct;
    unrelated views give large, incoherent flow); and going i -> j by the forward matches
    and back by the backward ones returns, in the median, within ``config.loop_max_cycle_px``
    of the start (two independent flows agree)."""
    cfg = config or GraphConfig()
    cand = _as_edges(candidates)[:, :4].astype(np.int32)
    M, s = len(cand), buffer.stride
    empty = (np.zeros((0, 5), np.int32), np.zeros((0, buffer.h, buffer.w, 2), np.float32), np.zeros((0, buffer.h, buffer.w), np.float32), [])
    if M == 0:
        return empty
    both = np.concatenate([cand, cand[:, [2, 3, 0, 1]]])
    # the checks judge the geometry: a provider's photometric factor (GuidedDIS) is applied
    # to the accepted edges' weights afterwards
    photometric = getattr(provider, "photometric", None)
    photometric = photometric if callable(photometric) else None
    targets, weights = provider.correspondences(buffer, both, photometric=False) if photometric else provider.correspondences(buffer, both)
    pred, valid, _ = reproject(buffer, both)
    checks, keep = [], []
    for m in range(M):
        conf, res = [], []
        for e in (m, m + M):
            good = valid[e] & (weights[e] >= 0.5)
            conf.append(good.sum() / max(valid[e].sum(), 1))
            res.append(float(np.median(np.linalg.norm(targets[e][good] - pred[e][good], axis=-1))) * s if good.any() else np.inf)
        f, b = m, m + M
        good = valid[f] & (weights[f] >= 0.5)
        start = np.stack(np.nonzero(good)[::-1], -1).astype(np.float64)  # (x, y) grid pixels of view i
        back, ok = _bilinear(targets[b].astype(np.float64), weights[b] >= 0.5, targets[f][good].astype(np.float64))
        cycle = float(np.median(np.linalg.norm(back[ok] - start[ok], axis=-1))) * s if ok.sum() >= 10 else np.inf
        accepted = min(conf) >= cfg.loop_min_confident and max(res) <= cfg.loop_max_residual_px and cycle <= cfg.loop_max_cycle_px
        checks.append(LoopCheck(tuple(int(v) for v in cand[m]), float(min(conf)), float(max(res)), cycle, bool(accepted)))
        if accepted:
            keep += [f, b]
    if not keep:
        return empty[:3] + (checks,)
    edges = np.concatenate([both[keep], np.full((len(keep), 1), LOOP, np.int32)], 1)
    targets, weights = targets[keep], weights[keep]
    if photometric:
        targets, weights = photometric(buffer, both[keep], targets, weights)
    return edges, targets, weights, checks
