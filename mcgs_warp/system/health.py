"""The health of each keyframe solve (:meth:`~mcgs_warp.system.tracker.Tracker.add_keyframe`):
whether it is a tracking failure, which the tracker then recovers from.

Inputs: the factor graph's correspondences of the new keyframe, the sensor-depth factors that
agree (:attr:`~mcgs_warp.system.window_factors.WindowFactors.geometric`), the solve's MCBA
statistics per round and the keypoint pose it started from. State: one record per solve
(:attr:`SolveHealth.records`, checkpointed with the tracker's books), from which the run's
metrics come (``confident_fraction``, ``tracking_failures``, :mod:`.outputs`).
"""

from __future__ import annotations

import numpy as np


class SolveHealth:
    """Health records of the keyframe solves (module docstring). ``config``: the run's
    tracking section (``min_confident``, ``max_residual_ratio``, ``correspondences``)."""

    def __init__(self, graph, buffer, rig, config):
        self.graph = graph
        self.buf = buffer
        self.rig = rig
        self.cfg = config
        self.records: list = []  # per keyframe solve (a recovered keyframe has two): frame, confident fraction, residual level, accepted steps, failure (why, or None)

    @property
    def failures(self) -> list:
        """Frame index of every keyframe whose solve was a tracking failure (once each)."""
        return sorted({h["frame"] for h in self.records if h["failure"]})

    def confident_fractions(self, k: int, geometric=None) -> tuple[float, list]:
        """Fraction of keyframe ``k``'s grid pixels with a confident (weight > 0.5)
        correspondence to another keyframe, or whose sensor depth the other keyframes' depth
        agrees with (``geometric``: the solve's (window, depth-alignment factors) or None):
        over all cameras, and per camera [C]."""
        C, s = len(self.rig), self.buf.stride
        area = np.array([(c.height // s) * (c.width // s) for c in self.rig.cameras], np.float64)
        rows = [n for n, e in enumerate(self.graph.edges) if e[0] == k and e[2] != k]
        linked = np.zeros((C, self.buf.h, self.buf.w), bool)
        if rows:
            edges = self.graph.edges[rows]
            _, w = self.graph.correspondences(edges)
            for e, wt in zip(edges, w):
                linked[int(e[1])] |= wt > 0.5
        if geometric is not None and k in geometric[0]:  # sensor depth that agrees (and places the keyframe) counts as a confident match
            keyframes, f = geometric
            ok = f.agreement(self.buf.get_poses()[keyframes], keyframes.index(k))
            for dy in range(f.step):
                for dx in range(f.step):
                    linked[f.ci[ok], np.minimum(f.ys[ok] + dy, self.buf.h - 1), np.minimum(f.xs[ok] + dx, self.buf.w - 1)] = True
        per = linked.sum(axis=(1, 2)) / np.maximum(area, 1)
        return float(linked.sum()) / max(area.sum(), 1), [round(float(f), 4) for f in per]

    def check(self, k: int, rounds: list, anchor=None, geometric=None) -> str | None:
        """Why the solve that added keyframe ``k`` (``rounds``: its ``(MCBAStats, weight)``
        per round) is a tracking failure, or None: no MCBA step accepted in any round, too few
        confident correspondences, or a final robust cost per unit of correspondence weight
        far above the run's usual level. Recorded with ``anchor``, the keypoint pose it
        started from (PnPResult or None)."""
        th = self.cfg
        frac, per_camera = self.confident_fractions(k, geometric)
        stats, weight = rounds[-1]
        level = stats.dense_cost[-1] / max(weight, 1e-9) if stats.dense_cost else float("nan")  # the other classes' weights change over a run
        healthy = [h["residual"] for h in self.records if not h["failure"] and np.isfinite(h["residual"])]
        usual = float(np.median(healthy)) if len(healthy) >= 3 else None
        why = None
        if all(st.accepted == 0 for st, _ in rounds) and any(st.cost for st, _ in rounds):
            why = "no MCBA step accepted"
        elif frac < th.min_confident and th.correspondences != "none":
            why = f"only {100 * frac:.1f} % of its pixels have a confident correspondence (tracking.min_confident {100 * th.min_confident:g} %)"
        elif usual is not None and np.isfinite(level) and level > th.max_residual_ratio * usual:
            why = f"residual {level:.3g} is {level / usual:.0f}x the run's median (tracking.max_residual_ratio {th.max_residual_ratio:g})"
        self.records.append({"keyframe": k, "frame": int(self.buf.frame_index[k]), "confident": round(frac, 4), "confident_per_camera": per_camera, "residual": float(level), "accepted": int(sum(st.accepted for st, _ in rounds)),
                             "keypoint_inliers": None if anchor is None else anchor.n_inliers, "keypoint_matches": None if anchor is None else anchor.n_matches,
                             "dense_sigma": None if stats.noise is None else round(float(np.sqrt(stats.noise.sigma2)), 5), "dense_kappa": None if stats.noise is None else round(stats.noise.kappa, 2),
                             "dense_disagreement": None if stats.disagreement is None else float(stats.disagreement),
                             "class_weights": [round(x, 4) for x in stats.scales], "failure": why})
        return why
