"""Front end: DIS flow and its confidence, keyframe selection, depth priors, the edge graph."""

import numpy as np

from mcgs_warp.ba.graph import CROSS_TIME, CROSS_VIEW, TEMPORAL, build_edges, camera_overlap
from mcgs_warp.frontend.depth import ConstantDepth, SensorDepth, default_prior, grid_depth
from mcgs_warp.frontend.flow import DISFlow, GroundTruthFlow
from mcgs_warp.frontend.keyframes import KeyframeSelector
from problems import Problem


def test_dis_correspondences_agree_with_ground_truth(synthetic_seq):
    P = Problem(synthetic_seq, [0, 1], cross_view=False, radius=1)
    temporal = P.edges[P.edges[:, 4] == TEMPORAL]
    gt_t, gt_w = GroundTruthFlow([synthetic_seq[0].depths, synthetic_seq[1].depths], P.true_poses).correspondences(P.buf, temporal)
    dis_t, dis_w = DISFlow().correspondences(P.buf, temporal)
    assert dis_w.min() >= 0 and dis_w.max() <= 1
    err = np.linalg.norm(dis_t - gt_t, axis=-1) * P.buf.stride  # full-resolution px
    both = gt_w > 0
    confident = both & (dis_w > 0.5)
    assert confident.sum() > 0.5 * both.sum()
    assert np.median(err[confident]) < 0.5
    assert np.mean(err[confident]) < np.mean(err[both])  # the confidence singles out bad flow


def test_keyframe_selector_measures_motion(synthetic_seq):
    sel = KeyframeSelector(DISFlow(preset="fast"), threshold=8.0)
    f0, f1, f4 = synthetic_seq[0], synthetic_seq[1], synthetic_seq[4]
    same, m0 = sel.is_keyframe(f0.images, f0.images)
    small, m1 = sel.is_keyframe(f0.images, f1.images)
    big, m4 = sel.is_keyframe(f0.images, f4.images)
    assert m0 < 0.2 and not same
    assert m0 < m1 < m4 and big and not small


def test_depth_priors(synthetic_seq):
    f = synthetic_seq[2]
    rig = synthetic_seq.rig
    assert isinstance(default_prior(synthetic_seq), SensorDepth)
    g = grid_depth(SensorDepth()(f, rig), rig, 8, (30, 40))
    assert g.shape == (3, 30, 40) and g[1, 5, 7] == f.depths[1][5 * 8 + 4, 7 * 8 + 4]
    c = grid_depth(ConstantDepth(2.5)(f, rig), rig, 8, (30, 40))
    assert np.all(c == 2.5)


def test_edge_graph(synthetic_seq):
    rig = synthetic_seq.rig
    overlap = camera_overlap(rig)
    assert overlap[0, 1] > 0.05 and overlap[0, 2] > 0.05  # front sees into both side cameras
    edges = build_edges([3, 4, 5, 6], 3, overlap, radius=2, cross_time=True)
    e = {tuple(x) for x in edges.tolist()}
    assert (3, 0, 5, 0, TEMPORAL) in e and (5, 0, 3, 0, TEMPORAL) in e  # both directions
    assert (3, 0, 6, 0, TEMPORAL) not in e  # beyond the radius
    assert (4, 0, 4, 1, CROSS_VIEW) in e and (4, 1, 4, 0, CROSS_VIEW) in e
    assert (4, 0, 5, 2, CROSS_TIME) in e
    assert all(not (i == j and a == b) for i, a, j, b, _ in e)
    pairs = {(a, b) for i, a, j, b, k in e if k == CROSS_VIEW}
    assert pairs == {(a, b) for a in range(3) for b in range(3) if a != b and overlap[a, b] >= 0.05}
    assert len(build_edges([0, 1], 3, None)) == 6  # temporal only without overlap information


def test_sliding_window():
    from mcgs_warp.ba.graph import sliding_window

    assert sliding_window(3, 8) == [0, 1, 2]
    assert sliding_window(12, 8) == list(range(4, 12))
    assert sliding_window(0, 8) == []
