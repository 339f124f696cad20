"""The global-BA backend (paper Fig. 3, bottom; DROID-SLAM's ``DroidBackend``): after the last
frame, one MCBA over every keyframe on long edges between overlapping views and on confirmed
loop edges (:meth:`Backend.run`).

Its inputs are the tracking stage's public parts: its factor graph (which it extends with the
long and loop edges), its correspondences (:meth:`~mcgs_warp.system.tracker.Tracker.measure`,
the guided flow that confirms loops) and its solve
(:meth:`~mcgs_warp.system.tracker.Tracker.solve`, through which the keyframe buffer's poses and
depths move: the tracker alone writes them). Its settings are ``refinement.global_ba_*``
(:class:`~mcgs_warp.system.config.RefinementConfig`; loop confirmation's are the graph's,
``tracking.graph.loop_*``). Its state is the loop check of every revisit candidate it examined
(:attr:`Backend.loops`); its output what the map must follow.
"""

from __future__ import annotations

from dataclasses import replace

from .config import RefinementConfig
from .memory import release_freed_memory
from .tracker import Tracker


class Backend:
    """Global MCBA with loop closure over a tracker's keyframes (module docstring).
    ``tracker``: the tracking stage; ``config``: the run's ``refinement`` section."""

    def __init__(self, tracker: Tracker, config: RefinementConfig):
        self.tracker = tracker
        self.iterations = config.global_ba_iterations  # LM iterations (0: no global BA)
        self.radius = config.global_ba_radius  # keyframes: how far apart long edges link views
        self.min_overlap = config.global_ba_min_overlap  # a long edge's reprojected overlap, both ways
        self.loops: list = []  # LoopCheck of every revisit candidate :meth:`run` examined

    @property
    def active(self) -> bool:
        """Whether there is a global BA to run: iterations and at least two keyframes."""
        return bool(self.iterations) and len(self.tracker.buf) > 1

    @property
    def confirmed_loops(self) -> int:
        """How many of the revisit candidates :meth:`run` examined it confirmed (loop edges added)."""
        return sum(bool(c.accepted) for c in self.loops)

    def run(self) -> list:
        """The offline MCBA over every keyframe: long edges between overlapping views up to
        :attr:`radius` keyframes apart, then confirmed loop edges, matched guided by the
        online solution, :attr:`iterations` LM iterations. Without exact depth the prior's
        weight is 0: an inexact prior, JDSA-scaled to the online estimate, would only hold
        that estimate in place. Returns what the map must follow
        (:meth:`~mcgs_warp.system.tracker.Tracker.take_update`)."""
        tracker = self.tracker
        graph, everything = tracker.graph, list(range(len(tracker.buf)))
        long_edges = replace(graph.cfg, max_per_view=2 * self.radius, min_overlap=self.min_overlap)
        graph.update_window(everything, cross_view=tracker.overlap is not None, max_gap=self.radius, config=long_edges)
        tracker.measure(guided_new=True)
        self.loops = graph.close_loops(tracker.guided_flow)
        release_freed_memory()  # the matching's temporaries, before the solve's arrays over every edge
        online = tracker.mcba.cfg
        offline = replace(online, iterations=self.iterations, prior_weight=online.prior_weight if tracker.exact_depth else 0.0)
        tracker.solve(everything, guided_new=True, config=offline)
        return tracker.take_update()
