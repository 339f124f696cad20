"""The global-BA backend (:class:`~mcgs_warp.system.backend.Backend`) on a stand-in tracker, no
SLAM run: its settings come from the run configuration's ``refinement`` section, and one
:meth:`~mcgs_warp.system.backend.Backend.run` extends the graph with long edges by those
settings, has them matched guided, confirms loops with the guided flow and solves every
keyframe with the offline iterations and prior weight."""

from types import SimpleNamespace

import pytest

from mcgs_warp.ba.edges import GraphConfig
from mcgs_warp.ba.mcba import MCBAConfig
from mcgs_warp.errors import InputError
from mcgs_warp.system.backend import Backend
from mcgs_warp.system.config import load_run_config


class StandInTracker:
    """The tracker's public parts the backend uses, recording every call in order."""

    def __init__(self, n_keyframes: int, exact_depth: bool, overlap=None):
        self.calls: list = []
        self.buf = [None] * n_keyframes
        self.overlap, self.exact_depth = overlap, exact_depth
        self.guided_flow = object()
        self.mcba = SimpleNamespace(cfg=MCBAConfig(iterations=7, prior_weight=30.0))
        self.loop_checks = [SimpleNamespace(accepted=True), SimpleNamespace(accepted=False), SimpleNamespace(accepted=True)]
        tracker = self

        class Graph:
            cfg = GraphConfig(min_overlap=0.3, max_per_view=4, loop_max_per_view=3)

            def update_window(self, keyframes, cross_view=True, max_gap=None, config=None):
                tracker.calls.append(("update_window", keyframes, cross_view, max_gap, config))

            def close_loops(self, provider):
                tracker.calls.append(("close_loops", provider))
                return tracker.loop_checks

        self.graph = Graph()

    def measure(self, refresh=(), guided_new=False):
        self.calls.append(("measure", refresh, guided_new))

    def solve(self, keyframes, fresh=(), guided_new=False, config=None):
        self.calls.append(("solve", keyframes, fresh, guided_new, config))

    def take_update(self):
        self.calls.append(("take_update",))
        return ["the updates"]


def _refinement(tmp_path, text):
    path = tmp_path / "run.yaml"
    path.write_text(text)
    return load_run_config(path).refinement


def test_settings_come_from_the_refinement_section(tmp_path):
    default = Backend(StandInTracker(3, False), load_run_config().refinement)
    assert default.loops == [] and default.confirmed_loops == 0  # before run
    assert (default.iterations, default.radius, default.min_overlap) == (4, 6, 0.1)  # 0.1: the long edges' overlap the tracker's module constant had
    rc = _refinement(tmp_path, "refinement:\n  global_ba_iterations: 3\n  global_ba_radius: 5\n  global_ba_min_overlap: 0.25\n")
    backend = Backend(StandInTracker(3, False), rc)
    assert (backend.iterations, backend.radius, backend.min_overlap) == (3, 5, 0.25)
    with pytest.raises(InputError, match="global_ba_min_overlap"):
        _refinement(tmp_path, "refinement:\n  global_ba_min_overlap: 1.5\n")


def test_active_needs_iterations_and_two_keyframes(tmp_path):
    assert Backend(StandInTracker(2, False), load_run_config().refinement).active
    assert not Backend(StandInTracker(1, False), load_run_config().refinement).active
    assert not Backend(StandInTracker(2, False), _refinement(tmp_path, "refinement:\n  global_ba_iterations: 0\n")).active


@pytest.mark.parametrize("exact_depth", [False, True])
def test_run_links_long_edges_closes_loops_and_solves_every_keyframe(tmp_path, exact_depth):
    tracker = StandInTracker(5, exact_depth, overlap="rig overlap")
    backend = Backend(tracker, _refinement(tmp_path, "refinement:\n  global_ba_iterations: 3\n  global_ba_radius: 5\n  global_ba_min_overlap: 0.25\n"))
    assert backend.run() == ["the updates"]
    assert [c[0] for c in tracker.calls] == ["update_window", "measure", "close_loops", "solve", "take_update"]
    _, keyframes, cross_view, max_gap, long_edges = tracker.calls[0]
    assert keyframes == [0, 1, 2, 3, 4] and cross_view and max_gap == 5
    assert long_edges == GraphConfig(min_overlap=0.25, max_per_view=10, loop_max_per_view=3)  # 2 x radius partners; the graph's other settings kept
    assert tracker.calls[1] == ("measure", (), True)
    assert tracker.calls[2] == ("close_loops", tracker.guided_flow)
    assert backend.loops == tracker.loop_checks and backend.confirmed_loops == 2
    _, keyframes, fresh, guided_new, offline = tracker.calls[3]
    assert keyframes == [0, 1, 2, 3, 4] and fresh == () and guided_new
    assert offline == MCBAConfig(iterations=3, prior_weight=30.0 if exact_depth else 0.0)  # an inexact prior would hold the online estimate
    assert tracker.mcba.cfg.iterations == 7  # the online solves' settings are left alone


def test_run_without_cross_view_edges(tmp_path):
    tracker = StandInTracker(3, False, overlap=None)
    Backend(tracker, load_run_config().refinement).run()
    assert tracker.calls[0][2] is False
