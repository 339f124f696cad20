"""The factor graph: edges chosen by view overlap, their bookkeeping, and loop closure.

The loop tests use the synthetic loop sequence (40 frames, 0.9 m apart, ending 0.9 m
before its start) as keyframes with exact depth, and an artificial odometry drift: each
step's relative motion is off by 1 cm sideways and 0.08 deg of yaw, so the last keyframe
ends 0.45 m and 3.1 deg from where it should be relative to the first. The normal edges'
correspondences are the drifted geometry's own reprojections (the odometry agrees with
itself), so only a loop edge, matched in the images, can see the drift."""

import numpy as np
import pytest

from mcgs_warp.ba import edges as E
from mcgs_warp.ba import graph as G
from mcgs_warp.ba import loops as L
from mcgs_warp.ba.mcba import MCBA, MCBAConfig
from mcgs_warp.buffer import KeyframeBuffer
from mcgs_warp.data.synthetic import generate, loop_trajectory
from mcgs_warp.frontend.depth import grid_depth
from mcgs_warp.frontend.flow import DISFlow, GuidedDIS
from mcgs_warp.geometry import se3_exp, yaw_pitch_roll

STRIDE = 8
DRIFT_STEP = np.array([0.0, 0.01, 0.0, 0.0, 0.0, np.radians(0.08)])  # (rho m, phi rad), body frame, per keyframe


@pytest.fixture(scope="module")
def loop_seq(tmp_path_factory):
    """40 keyframe-like samples of the full 35.5 m room loop (0.9 m apart)."""
    full_loop = loop_trajectory(40, max_step=np.inf)
    return generate(tmp_path_factory.mktemp("graph") / "loop", n_cameras=3, seed=1, progress=False, trajectory=full_loop)


def make_buffer(seq, frames, poses=None) -> KeyframeBuffer:
    """Keyframes ``frames`` of ``seq`` with exact grid depth and (default) true poses."""
    buf = KeyframeBuffer(seq.rig, stride=STRIDE, capacity=len(frames))
    for n, k in enumerate(frames):
        f = seq[k]
        grid = grid_depth(f.depths, seq.rig, STRIDE, (buf.h, buf.w))
        T = seq.groundtruth.poses[k] if poses is None else poses[n]
        buf.add(k, f.timestamp, f.images, T, np.where(grid > 0, 1.0 / np.maximum(grid, 1e-6), 0.0))
    return buf


def drifted(true: np.ndarray) -> np.ndarray:
    """Rig poses [K,4,4] chained from the true relative motions, each off by DRIFT_STEP."""
    T = true.copy()
    for k in range(1, len(T)):
        T[k] = T[k - 1] @ np.linalg.inv(true[k - 1]) @ true[k] @ se3_exp(DRIFT_STEP)
    return T


def end_to_start_error(poses: np.ndarray, true: np.ndarray):
    """Error of the last keyframe's pose relative to the first: (m, deg)."""
    D = np.linalg.inv(np.linalg.inv(true[0]) @ true[-1]) @ (np.linalg.inv(poses[0]) @ poses[-1])
    return np.linalg.norm(D[:3, 3]), np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))


class Reprojection:
    """Correspondences that agree with the buffer's current geometry (the drifted odometry)."""

    def correspondences(self, buffer, edges):
        uv, valid, _ = E.reproject(buffer, edges)
        return uv.astype(np.float32), valid.astype(np.float32)


class Recording:
    """A provider that stamps each computed edge with a call counter, to see what ran."""

    def __init__(self):
        self.calls = []

    def correspondences(self, buffer, edges):
        self.calls.append([tuple(int(v) for v in e[:4]) for e in edges])
        t = np.full((len(edges), buffer.h, buffer.w, 2), len(self.calls), np.float32)
        return t, np.ones((len(edges), buffer.h, buffer.w), np.float32)


class Noisy:
    """Wraps a provider and shakes its targets (1 reduced px rms), keeping its confidence."""

    def __init__(self, provider):
        self.provider, self.rng = provider, np.random.default_rng(0)

    def correspondences(self, buffer, edges):
        t, w = self.provider.correspondences(buffer, edges)
        return t + self.rng.normal(0.0, 1.0, t.shape).astype(np.float32), w


@pytest.fixture(scope="module")
def loop_problem(loop_seq):
    """The drifted loop buffer, its true poses and a graph with overlap-chosen normal edges."""
    buf = make_buffer(loop_seq, range(len(loop_seq)))
    true = buf.get_poses()
    buf.set_poses(drifted(true))
    graph = G.FactorGraph(buf, E.camera_overlap(loop_seq.rig, stride=STRIDE))
    graph.update_window(range(len(buf)), cross_time=True, max_gap=4)
    graph.compute(Reprojection())
    return buf, true, graph


def test_edges_follow_view_overlap_not_index(loop_seq):
    """Keyframes: the start, 12 m further down the room, and the last (back near the start).
    Index distance links 0-1 and 1-2; the views link 0 and 2 (every camera) and nothing else:
    keyframe 1 sees what keyframe 0 sees far ahead, but not the other way round."""
    buf = make_buffer(loop_seq, [0, 14, 39])
    pairs = [(a, c, b, c) for c in range(3) for a, b in [(0, 1), (1, 0), (1, 2), (2, 1), (0, 2), (2, 0)]]
    ov = E.view_overlap(buf, pairs)[0].reshape(3, 6)
    assert np.all(ov[:, :4].reshape(3, 2, 2).min(-1) < 0.1) and np.all(ov[:, 4:] > 0.3), ov
    edges = E.overlap_edges(buf, [0, 1, 2], cross_view=False)
    assert {(int(i), int(j)) for i, _, j, _, _ in edges} == {(0, 2), (2, 0)}, edges
    assert set(map(int, edges[:, 1])) == {0, 1, 2} and set(map(int, edges[:, 4])) == {E.TEMPORAL}
    index_pairs = {(int(i), int(j)) for i, _, j, _, _ in E.build_edges([0, 1, 2], 3, radius=1, cross_view=False)}
    assert index_pairs == {(0, 1), (1, 0), (1, 2), (2, 1)}


def test_opposite_views_are_not_linked(loop_seq):
    """Half-way round the loop the rig faces back down the room: its front view overlaps the
    start's geometrically (the same floor and walls, seen from the other end), but the two
    look in opposite directions and no flow matches them."""
    buf = make_buffer(loop_seq, [0, 20])
    assert E.view_overlap(buf, [(1, 0, 0, 0), (0, 0, 1, 0)])[0].min() > 0.5
    assert len(E.overlap_edges(buf, [0, 1], cross_view=False)) == 0
    assert len(E.overlap_edges(buf, [0, 1], config=E.GraphConfig(max_angle=180.0), cross_view=False)) > 0


def test_edge_count_per_view_is_bounded_nearest_first(loop_seq):
    buf = make_buffer(loop_seq, range(6))
    edges = E.overlap_edges(buf, range(6), config=E.GraphConfig(max_per_view=2), cross_view=False)
    # consecutive keyframes overlap: nearest first, every view takes both neighbours, and
    # only the two end views (one neighbour each) have a slot left for a longer edge
    pairs = {(int(i), int(c), int(j)) for i, c, j, _, _ in edges}
    assert all((k, c, k + 1) in pairs and (k + 1, c, k) in pairs for k in range(5) for c in range(3))
    assert all(abs(i - j) == 1 or {i, j} == {0, 5} for i, _, j in pairs), sorted(pairs)
    per_view = np.unique(edges[:, :2], axis=0, return_counts=True)[1]
    assert per_view.max() == 2


def test_add_remove_refresh(loop_seq):
    buf = make_buffer(loop_seq, range(4))
    g = G.FactorGraph(buf, E.camera_overlap(loop_seq.rig, stride=STRIDE))
    prov = Recording()
    e = np.array([(0, 0, 1, 0), (1, 0, 0, 0), (1, 0, 2, 0), (2, 0, 1, 0), (1, 0, 1, 1)], np.int32)
    new = g.add(e)
    assert len(new) == 5 and list(new[:, 4]) == [E.TEMPORAL] * 4 + [E.CROSS_VIEW]
    assert len(g.add(e[:2])) == 0  # already active
    assert len(g.missing()) == 5
    with pytest.raises(KeyError):
        g.arrays()
    g.compute(prov)
    assert len(prov.calls) == 1 and len(g.missing()) == 0
    edges, t, w = g.arrays()
    assert edges.shape == (5, 5) and t.shape == (5, buf.h, buf.w, 2) and w.shape == (5, buf.h, buf.w)
    assert np.all(t == 1)
    # a window that drops keyframe 0: its edges are stored, not forgotten
    removed = g.remove(outside=[1, 2, 3])
    assert {tuple(r[:4]) for r in removed} == {(0, 0, 1, 0), (1, 0, 0, 0)}
    assert len(g) == 3 and len(g.stored) == 2 and (0, 0, 1, 0) not in g
    assert g.has_correspondences((0, 0, 1, 0))
    g.add(removed)  # comes back with its kept correspondences: nothing to compute
    assert len(g.missing()) == 0 and len(prov.calls) == 1
    # refresh: temporal edges touching keyframe 2 only; cross-view edges stay
    redo = g.refresh(prov, [2])
    assert {tuple(r[:4]) for r in redo} == {(1, 0, 2, 0), (2, 0, 1, 0)}
    t2, _ = g.correspondences([(1, 0, 2, 0), (0, 0, 1, 0), (1, 0, 1, 1)])
    assert t2[0].max() == 2 and t2[1].max() == 1 and t2[2].max() == 1
    # restricted arrays and forgetting
    assert {tuple(r[:4]) for r in g.arrays(keyframes=[0, 1])[0]} == {(0, 0, 1, 0), (1, 0, 0, 0), (1, 0, 1, 1)}
    g.remove(keyframes=[2], store=False)
    assert not g.has_correspondences((1, 0, 2, 0)) and len(g) == 3
    assert g.forget_keyframes([0]) == 2 and len(g) == 1 and len(g.stored) == 0
    # update_window: overlap-chosen edges among keyframes 1..3; the rest are stored
    new = g.update_window([1, 2, 3])
    assert len(new) and set(map(int, np.unique(new[:, [0, 2]]))) <= {1, 2, 3}
    assert {tuple(r[:4]) for r in g.missing()} == {tuple(r[:4]) for r in new}


def test_checkpoint_round_trip(loop_seq, tmp_path):
    buf = make_buffer(loop_seq, range(4))
    g = G.FactorGraph(buf)
    g.add([(0, 0, 1, 0), (1, 0, 0, 0)])
    g.add([(2, 1, 3, 1, E.LOOP)])
    g.compute(Recording(), [(0, 0, 1, 0), (2, 1, 3, 1)])
    g.remove([(0, 0, 1, 0)])  # stored, with correspondences
    np.savez(tmp_path / "ckpt.npz", **g.state_arrays())
    h = G.FactorGraph(buf)
    with np.load(tmp_path / "ckpt.npz") as z:
        h.load_state_arrays({k: z[k] for k in z.files})
    assert np.array_equal(h.edges, g.edges) and np.array_equal(h.stored, g.stored)
    assert np.array_equal(h.missing(), g.missing()) and h.missing()[0, :4].tolist() == [1, 0, 0, 0]
    for e in [(0, 0, 1, 0), (2, 1, 3, 1)]:
        for a, b in zip(h.correspondences([e]), g.correspondences([e])):
            assert np.array_equal(a, b)
    assert h.edges[-1, 4] == E.LOOP
    assert {tuple(e[:4]) for e, _, _ in h.items()} == {(0, 0, 1, 0), (2, 1, 3, 1)}


def test_measured_weight_sums_every_edge_leaving_the_keyframe(loop_seq, tmp_path):
    """The per-source index gives what a scan over all edges gives, after storing,
    forgetting and a checkpoint round trip."""
    buf = make_buffer(loop_seq, range(4))
    g = G.FactorGraph(buf)
    rng = np.random.default_rng(0)
    edges = [(0, 0, 1, 0), (0, 1, 1, 1), (0, 0, 2, 0), (1, 0, 0, 0), (2, 2, 0, 2), (0, 2, 0, 1)]
    t = np.zeros((len(edges), buf.h, buf.w, 2), np.float32)
    g.add(edges, t, rng.uniform(size=(len(edges), buf.h, buf.w)).astype(np.float32))
    g.remove([(0, 1, 1, 1)])  # stored: still measured
    g.forget([(0, 0, 2, 0)])  # forgotten: no longer

    def scan(k):
        out = np.zeros((3, buf.h, buf.w), np.float32)
        for e, _, w in g.items():
            if e[0] == k:
                out[e[1]] += w
        return out

    for k in range(4):
        assert np.array_equal(g.measured_weight(k, 3), scan(k))
    assert g.measured_weight(0, 3)[1].max() > 0 and not g.measured_weight(3, 3).any()
    np.savez(tmp_path / "ckpt.npz", **g.state_arrays())
    h = G.FactorGraph(buf)
    with np.load(tmp_path / "ckpt.npz") as z:
        h.load_state_arrays({k: z[k] for k in z.files})
    for k in range(4):
        assert np.array_equal(h.measured_weight(k, 3), g.measured_weight(k, 3))


def test_checkpoint_segments_write_each_correspondence_once(loop_seq, tmp_path):
    """With a segment store a checkpoint writes only the correspondences that changed since
    the last one; reloading gives back every edge's current correspondences, and segments
    no checkpoint refers to any more are deleted."""
    buf = make_buffer(loop_seq, range(4))
    store = tmp_path / "ckpt.corr"
    g = G.FactorGraph(buf)
    rec = Recording()
    g.add([(0, 0, 1, 0), (1, 0, 0, 0), (1, 1, 2, 1)])
    g.compute(rec)
    first = g.state_arrays(store)
    assert sorted(p.name for p in store.iterdir()) == ["seg_000000.npz"]
    again = g.state_arrays(store)  # nothing changed: nothing written
    assert sorted(p.name for p in store.iterdir()) == ["seg_000000.npz"]
    assert np.array_equal(first["graph_segment"], again["graph_segment"])
    g.compute(rec, [(1, 1, 2, 1)])  # one edge re-estimated, one new
    g.add([(2, 0, 3, 0)])
    g.compute(rec)
    arrays = g.state_arrays(store)
    with np.load(store / "seg_000001.npz") as z:
        assert len(z["targets"]) == 2  # only the two that changed
    h = G.FactorGraph(buf)
    h.load_state_arrays(arrays, store)
    for e in [(0, 0, 1, 0), (1, 0, 0, 0), (1, 1, 2, 1), (2, 0, 3, 0)]:
        for a, b in zip(h.correspondences([e]), g.correspondences([e])):
            assert np.array_equal(a, b)
    assert h.correspondences([(1, 1, 2, 1)])[0].max() == 2  # the re-estimate, not the first
    g.forget([(0, 0, 1, 0), (1, 0, 0, 0)])
    g.compute(rec, [(1, 1, 2, 1), (2, 0, 3, 0)])
    g.state_arrays(store)
    assert g.prune_store(store) == 2 and sorted(p.name for p in store.iterdir()) == ["seg_000002.npz"]
    with pytest.raises(ValueError, match="segment"):
        G.FactorGraph(buf).load_state_arrays(arrays)  # the folder is needed
    # a segment that falls below half live is compacted: its live rows move to the new one
    dense = tmp_path / "dense.corr"
    d = G.FactorGraph(buf)
    four = [(0, 0, 1, 0), (1, 0, 0, 0), (1, 1, 2, 1), (2, 1, 1, 1)]
    d.add(four)
    d.compute(rec)
    d.state_arrays(dense)
    d.compute(rec, four[:3])  # three of four re-matched: segment 0 keeps one live row of four
    moved = d.state_arrays(dense)
    assert d.prune_store(dense) == 1 and sorted(p.name for p in dense.iterdir()) == ["seg_000001.npz"]
    e = G.FactorGraph(buf)
    e.load_state_arrays(moved, dense)
    for a, b in zip(e.correspondences(four), d.correspondences(four)):
        assert np.array_equal(a, b)
    other = tmp_path / "elsewhere.corr"
    moved = g.state_arrays(other)  # a new folder gets every current correspondence
    k = G.FactorGraph(buf)
    k.load_state_arrays(moved, other)
    assert np.array_equal(k.correspondences()[1], g.correspondences()[1])


def test_loop_edge_found_and_global_ba_closes_the_loop(loop_problem):
    buf, true, graph = loop_problem
    K = len(buf)
    before = end_to_start_error(buf.get_poses(), true)
    assert before[0] > 0.4 and before[1] > 3.0, before
    assert not any({int(e[0]), int(e[2])} == {0, K - 1} for e in graph.edges)  # the odometry never links them
    T0, disp0 = buf.get_poses(), buf.disp.numpy().copy()

    checks = graph.close_loops(GuidedDIS(DISFlow()))
    loops = graph.edges[graph.edges[:, 4] == E.LOOP]
    assert any(c.accepted and {c.edge[0], c.edge[2]} == {0, K - 1} for c in checks), checks
    assert all(c.edge[0] - c.edge[2] > graph.cfg.loop_min_gap for c in checks)
    assert len(loops) >= 2 and {(int(i), int(j)) for i, _, j, _, _ in loops} >= {(K - 1, 0), (0, K - 1)}

    edges, targets, weights = graph.arrays()
    errors = {}
    for with_loops in (False, True):
        buf.set_poses(T0)
        buf.disp.assign(disp0)
        sel = np.ones(len(edges), bool) if with_loops else edges[:, 4] != E.LOOP
        MCBA(buf, MCBAConfig(iterations=6)).solve(edges[sel], targets[sel], weights[sel], keyframes=list(range(K)))
        errors[with_loops] = end_to_start_error(buf.get_poses(), true)
    buf.set_poses(T0)
    buf.disp.assign(disp0)
    assert errors[False][0] > 0.9 * before[0]  # the normal edges agree with the drift: it stays
    assert errors[True][0] < 0.5 * errors[False][0], errors
    assert errors[True][1] < 0.5 * errors[False][1], errors


def test_loop_closure_with_estimated_depth(loop_seq):
    """The same drifted loop, but every keyframe's depth is an estimate (10 % log-normal
    noise per grid pixel, and 15 % too far on the last keyframes, as a drifting scale would
    leave it): the loop is still confirmed in the images (GuidedDIS predicts with the noisy
    depth) and global BA with it still removes most of the drift, depth included."""
    buf = make_buffer(loop_seq, range(len(loop_seq)))
    true = buf.get_poses()
    rng = np.random.default_rng(5)
    disp = buf.disp.numpy()
    K = len(buf)
    far = np.where(np.arange(buf.capacity) >= K - 5, 1 / 1.15, 1.0)[:, None, None, None]
    buf.disp.assign((disp * far * np.exp(0.1 * rng.normal(size=disp.shape))).astype(np.float32))
    buf.set_poses(drifted(true))
    graph = G.FactorGraph(buf, E.camera_overlap(loop_seq.rig, stride=STRIDE))
    graph.update_window(range(K), cross_time=True, max_gap=4)
    graph.compute(Reprojection())  # the odometry agrees with its own (noisy) geometry
    before = end_to_start_error(buf.get_poses(), true)
    checks = graph.close_loops(GuidedDIS(DISFlow()))
    assert any(c.accepted and {c.edge[0], c.edge[2]} == {0, K - 1} for c in checks), checks
    edges, targets, weights = graph.arrays()
    MCBA(buf, MCBAConfig(iterations=6)).solve(edges, targets, weights, keyframes=list(range(K)))
    after = end_to_start_error(buf.get_poses(), true)
    # measured: 0.45 m / 3.1 deg -> 0.17 m / 1.3 deg (exact depth: see the test above)
    assert after[0] < 0.5 * before[0] and after[1] < 0.5 * before[1], (before, after)


def test_false_loop_candidates_are_rejected(loop_problem):
    buf, _, graph = loop_problem
    K = len(buf)
    cfg, guided = graph.cfg, GuidedDIS(DISFlow())
    T0 = buf.get_poses()
    cand = L.loop_candidates(buf, config=cfg)
    assert len(cand) and all({int(c[0]), int(c[2])} == {0, K - 1} for c in cand), cand
    # the images of the last keyframe come from the far end of the loop: the poses still
    # say "revisit", the flow finds no consistent match
    images = buf.images[K - 1]
    buf.images[K - 1] = buf.images[K // 2]
    try:
        edges, _, _, checks = L.confirm_loops(buf, cand, guided, cfg)
    finally:
        buf.images[K - 1] = images
    assert len(edges) == 0 and all(c.confident < cfg.loop_min_confident for c in checks), checks
    # a corrupted flow (right images, targets shaken): the two directions disagree
    edges, _, _, checks = L.confirm_loops(buf, cand, Noisy(guided), cfg)
    assert len(edges) == 0 and all(c.cycle_px > cfg.loop_max_cycle_px for c in checks), checks
    # the last rig set down at the start but turned around: the front cameras face away
    # (no candidate), the side cameras' images do not match (rejected)
    away = T0.copy()
    turn = np.eye(4)
    turn[:3, :3] = yaw_pitch_roll(np.pi, 0.0, 0.0)
    away[K - 1] = T0[0] @ turn
    away[K - 1][:3, 3] += [0.2, 0.1, 0.0]
    buf.set_poses(away)
    try:
        cand = L.loop_candidates(buf, config=cfg)
        edges, _, _, checks = L.confirm_loops(buf, cand, guided, cfg)
    finally:
        buf.set_poses(T0)
    assert not any(c[1] == 0 and c[3] == 0 for c in cand), cand
    assert len(edges) == 0, checks


def test_a_keyframe_without_overlapping_views_is_still_linked(synthetic_seq):
    """The tracker's graph keeps each camera of a new keyframe linked to the previous keyframe
    when the overlap rule found it no partner (it would otherwise not be tracked at all), and
    adds nothing for cameras that have one; the graph's bookkeeping asks without adding."""
    from mcgs_warp.system.config import RunConfig
    from mcgs_warp.system.slam import SLAM

    slam = SLAM(synthetic_seq, RunConfig()).tracker
    C = len(synthetic_seq.rig)
    slam.graph.add([(1, 0, 0, 0), (0, 0, 1, 0)])
    assert slam.graph.link_to_previous(1, C) == list(range(1, C))
    keys = {tuple(int(v) for v in e[:4]) for e in slam.graph.edges}
    assert keys == {(1, c, 0, c) for c in range(C)} | {(0, c, 1, c) for c in range(C)}
    assert slam.graph.link_to_previous(1, C) == []
    assert len(slam.graph.edges) == 2 * C
    # asking which edges lack correspondences does not add unknown edges
    assert len(slam.graph.missing([(5, 0, 6, 0)])) == 1 and (5, 0, 6, 0) not in {tuple(int(v) for v in e[:4]) for e in slam.graph.stored}


def test_refresh_skips_edges_the_geometry_already_explains(loop_seq):
    """GuidedDIS.settled: with the true geometry and exact matches every edge is settled and
    refresh re-matches nothing; after keyframe 2 moves by 2 cm its edges are re-matched (and
    only those); a settled edge whose stored matches are off by 2 px is re-matched too."""
    from mcgs_warp.frontend.flow import GroundTruthFlow

    frames = [0, 1, 2, 3]
    buf = make_buffer(loop_seq, frames)
    g = G.FactorGraph(buf, None)
    e = np.array([(0, 0, 1, 0), (1, 0, 0, 0), (1, 0, 2, 0), (2, 0, 1, 0), (2, 0, 3, 0), (3, 0, 2, 0), (0, 1, 1, 1), (1, 1, 0, 1)], np.int32)
    g.add(e)
    gt = GroundTruthFlow([loop_seq[k].depths for k in frames], buf.get_poses())
    g.compute(gt)
    guided = GuidedDIS(DISFlow())
    _, t, w = g.arrays()
    assert guided.settled(buf, g.arrays()[0], t, w).all()

    class Counting(GuidedDIS):
        calls: list = []

        def correspondences(self, buffer, edges):
            Counting.calls += [tuple(int(v) for v in r[:4]) for r in edges]
            return gt.correspondences(buffer, edges)

    prov = Counting(DISFlow())
    assert len(g.refresh(prov, [0, 1, 2, 3])) == 0 and not Counting.calls
    T = buf.get_poses()
    T[2] = T[2] @ se3_exp(np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.0]))
    buf.set_poses(T)
    redo = {tuple(r[:4]) for r in g.refresh(prov, [0, 1, 2, 3])}
    assert redo == {(1, 0, 2, 0), (2, 0, 1, 0), (2, 0, 3, 0), (3, 0, 2, 0)} == set(Counting.calls)
    buf.set_poses(gt.T_w_b)
    t, w = g.correspondences([(0, 1, 1, 1)])
    g.set_correspondences(np.array([(0, 1, 1, 1, E.TEMPORAL)], np.int32), t + 2.0 / STRIDE, w)
    assert {tuple(r[:4]) for r in g.refresh(prov, [0])} == {(0, 1, 1, 1)}


def test_settled_edges_on_a_rig_with_a_smaller_camera(loop_seq):
    """GuidedDIS.settled on a rig whose second camera is smaller than the buffer's grid (its
    images cropped to 264x184, the same intrinsics): exact matches at the true geometry are
    settled, and moving a keyframe unsettles the edges of both cameras."""
    import dataclasses

    from mcgs_warp.frontend.flow import GroundTruthFlow
    from mcgs_warp.rig import Rig

    w, h = 264, 184
    cams = list(loop_seq.rig.cameras)
    cams[1] = dataclasses.replace(cams[1], width=w, height=h)
    rig = Rig(cams)
    frames = [0, 1]
    buf = KeyframeBuffer(rig, stride=STRIDE, capacity=2)
    depths = []
    for k in frames:
        f = loop_seq[k]
        images = [f.images[0], np.ascontiguousarray(f.images[1][:h, :w]), f.images[2]]
        d = [f.depths[0], np.ascontiguousarray(f.depths[1][:h, :w]), f.depths[2]]
        grid = grid_depth(d, rig, STRIDE, (buf.h, buf.w))
        buf.add(k, f.timestamp, images, loop_seq.groundtruth.poses[k], np.where(grid > 0, 1.0 / np.maximum(grid, 1e-6), 0.0))
        depths.append(d)
    assert (buf.h, buf.w) == (loop_seq.rig.cameras[0].height // STRIDE, loop_seq.rig.cameras[0].width // STRIDE)
    edges = np.array([(0, 0, 1, 0, E.TEMPORAL), (1, 1, 0, 1, E.TEMPORAL), (0, 1, 1, 1, E.TEMPORAL)], np.int32)
    t, wgt = GroundTruthFlow(depths, buf.get_poses()).correspondences(buf, edges)
    assert (wgt[1:, h // STRIDE :, :] == 0).all() and (wgt[1:] > 0).sum() > 100
    guided = GuidedDIS(DISFlow())
    assert guided.settled(buf, edges, t, wgt).all()
    T = buf.get_poses()
    T[1] = T[1] @ se3_exp(np.array([0.03, 0.0, 0.0, 0.0, 0.0, 0.0]))
    buf.set_poses(T)
    assert not guided.settled(buf, edges, t, wgt).any()
