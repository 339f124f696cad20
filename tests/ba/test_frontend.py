"""Front end: DIS flow and its confidence, keyframe selection, depth priors, the edge graph."""

import numpy as np
import pytest

from mcgs_warp.ba.edges import CROSS_TIME, CROSS_VIEW, TEMPORAL, build_edges, camera_overlap
from mcgs_warp.frontend.depth import NoDepth, SensorDepth, StereoDepth, choose_prior, grid_depth, upsample_inverse_depth, upsample_inverse_depth_guided
from mcgs_warp.frontend.flow import DISFlow, GroundTruthFlow
from mcgs_warp.frontend.keyframes import KeyframeSelector
from mcgs_warp.rig import CameraSpec
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


def test_dis_settings_of_the_slam_loop_beat_the_preset(synthetic_seq):
    """Full resolution (finest_scale 0) halves the median error of the medium preset (which
    stops at half resolution); small patches with weak smoothness, as the SLAM loop uses
    them, remove most gross errors on edges up to 4 frames apart (0.6 m)."""
    P = Problem(synthetic_seq, [0, 2, 4], cross_view=False)
    temporal = P.edges[P.edges[:, 4] == TEMPORAL]
    gt_t, gt_w = P.targets_for(temporal)

    def errors(dis):
        t, w = dis.correspondences(P.buf, temporal)
        ok = (w > 0.5) & (gt_w > 0)
        return np.linalg.norm(t - gt_t, axis=-1)[ok] * P.buf.stride  # full-resolution px

    preset, full, slam = errors(DISFlow()), errors(DISFlow(finest_scale=0)), errors(DISFlow(finest_scale=0, patch_size=4, smoothness=5.0))
    assert np.median(full) < 0.7 * np.median(preset), (np.median(full), np.median(preset))
    assert np.mean(slam) < 0.5 * np.mean(preset), (np.mean(slam), np.mean(preset))
    assert np.mean(slam) < 0.5 * np.mean(full), (np.mean(slam), np.mean(full))


def test_dis_edge_and_its_reverse_share_two_dis_runs(synthetic_seq):
    """An edge and its reverse come from the same two DIS runs and equal what each edge
    alone gives (flow(a, b) and flow(b, a), each with its own forward-backward check)."""
    from mcgs_warp.buffer import grid_pixels
    from mcgs_warp.frontend.flow import from_reduced, grid_targets, textured

    P = Problem(synthetic_seq, [0, 1], cross_view=False, radius=1)
    temporal = P.edges[P.edges[:, 4] == TEMPORAL]
    pairs = [e for e in temporal.tolist() if [e[2], e[3], e[0], e[1], e[4]] in temporal.tolist()]
    assert len(pairs) >= 2
    dis = DISFlow()
    calls = []
    real = dis.dis.calc
    dis.dis = type("Counting", (), {"calc": lambda self, a, b, f: calls.append(1) or real(a, b, f)})()
    t, w = dis.correspondences(P.buf, np.array(pairs, np.int32))
    assert len(calls) == len(pairs)  # two DIS runs per edge pair, not per edge
    for e, (i, ci, j, cj, _kind) in enumerate(pairs):
        alone = grid_targets(P.buf, ci, cj, *DISFlow().flow(P.buf.image(i, ci), P.buf.image(j, cj)))
        uv = grid_pixels(P.buf.rig.cameras[ci], P.buf.stride)
        gh, gw = uv.shape[:2]
        alone[1][:gh, :gw] *= textured(P.buf.image(i, ci), uv) & textured(P.buf.image(j, cj), from_reduced(alone[0][:gh, :gw], P.buf.stride))
        np.testing.assert_allclose(t[e], alone[0], atol=1e-5)
        np.testing.assert_allclose(w[e], alone[1], atol=1e-5)


def test_flat_patches_give_no_correspondence(synthetic_seq):
    """A flat region (overexposed sky) matches itself anywhere: the forward-backward check
    passes it, so the texture test must take its weight, raw and guided alike."""
    from mcgs_warp.frontend.flow import GuidedDIS

    P = Problem(synthetic_seq, [0, 1], cross_view=False, radius=1)
    h = P.buf.rig.cameras[0].height
    for k in (0, 1):  # the top third of camera 0 overexposed in both keyframes
        img = P.buf.image(k, 0).copy()
        img[: h // 3] = 1.0
        P.buf.images[k] = [img] + list(P.buf.images[k][1:])
    edges = np.array([[0, 0, 1, 0, TEMPORAL], [1, 0, 0, 0, TEMPORAL]], np.int32)
    for name, provider in (("raw", DISFlow()), ("guided", GuidedDIS(DISFlow()))):
        _, w = provider.correspondences(P.buf, edges)
        rows = (h // 3 - 4) // P.buf.stride  # grid rows whose 7x7 window is all sky
        assert np.all(w[:, :rows] == 0), name
        assert (w[:, rows + 2 : h // P.buf.stride] > 0.5).mean() > 0.5, name  # the textured rest still matches


def test_dis_reverse_of_different_sized_views(synthetic_seq):
    """Views of different sizes (a rig mixing cameras): both directions from one pair of DIS
    runs equal flow(a, b) and flow(b, a), each cropped to its own view."""
    a = synthetic_seq[0].images[0]
    b = np.ascontiguousarray(synthetic_seq[1].images[0][:200, :280])
    dis = DISFlow()
    (f_ab, c_ab), (f_ba, c_ba) = dis.flows(a, b)
    assert f_ab.shape == a.shape[:2] + (2,) and f_ba.shape == b.shape[:2] + (2,)
    for (f, c), (g, d) in (((f_ab, c_ab), dis.flow(a, b)), ((f_ba, c_ba), dis.flow(b, a))):
        np.testing.assert_allclose(f, g, atol=1e-5)
        np.testing.assert_allclose(c, d, atol=1e-5)


def test_keyframe_selector_measures_motion(synthetic_seq):
    sel = KeyframeSelector(DISFlow(preset="fast"), synthetic_seq.rig.cameras, threshold=8.0 / 180)
    f0, f1, f4 = synthetic_seq[0], synthetic_seq[1], synthetic_seq[4]
    same, m0 = sel.is_keyframe(f0.images, f0.images)
    small, m1 = sel.is_keyframe(f0.images, f1.images)
    big, m4 = sel.is_keyframe(f0.images, f4.images)
    assert m0 < 0.2 / 180 and not same
    assert m0 < m1 < m4 and big and not small


def test_keyframe_threshold_means_the_same_motion_at_any_resolution(synthetic_seq):
    """The mean flow is a view angle: the same two frames at twice the resolution (focal
    lengths doubled) measure the same, where in pixels they measured twice as much."""
    import cv2

    from mcgs_warp.data.resample import resampled_camera

    cams = synthetic_seq.rig.cameras
    big = [resampled_camera(c, 2 * c.width, 2 * c.height) for c in cams]
    a, b = synthetic_seq[0].images, synthetic_seq[3].images
    up = lambda imgs: [cv2.resize(im, None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR) for im in imgs]  # noqa: E731
    small = KeyframeSelector(DISFlow(), cams).mean_flow(a, b)
    large = KeyframeSelector(DISFlow(), big).mean_flow(up(a), up(b))
    assert small > 0.01 and abs(large / small - 1) < 0.1, (small, large)  # 0.0896 vs 0.0944 rad (DIS is not exactly scale-invariant); in pixels: 2x


def test_depth_priors(synthetic_seq):
    f = synthetic_seq[2]
    rig = synthetic_seq.rig
    g = grid_depth(SensorDepth()(f, rig), rig, 8, (30, 40))
    assert g.shape == (3, 30, 40) and g[1, 5, 7] == f.depths[1][5 * 8 + 4, 7 * 8 + 4]
    assert np.all(grid_depth(NoDepth()(f, rig), rig, 8, (30, 40)) == 0)


def test_stereo_depth_is_kept_per_frame(synthetic_seq, monkeypatch):
    """RigStereo.depth keeps the last KEEP frames' results (at sweep resolution, float32) and
    archives older ones in float16: asking again for every earlier keyframe, as the mapper
    does after global BA, sweeps nothing again; kept frames give exactly what a fresh
    RigStereo gives, archived ones the same within float16 rounding."""
    from mcgs_warp.frontend import stereo as S

    rig = synthetic_seq.rig
    st = S.RigStereo(rig, camera_overlap(rig, stride=8))
    monkeypatch.setattr(S, "KEEP", 3)
    sweeps = []
    real = st.pair_sweeps
    st.pair_sweeps = lambda key, images: sweeps.append(key) or real(key, images)
    frames = [synthetic_seq[k] for k in range(5)]
    for f in frames:
        st.depth(f.index, f.images)
    C = len(rig)
    assert len(sweeps) == 5 * C  # one request per camera and frame
    d2, c2 = st.depth(frames[2].index, frames[2].images)  # kept
    d0, c0 = st.depth(frames[0].index, frames[0].images)  # archived (KEEP 3)
    assert len(sweeps) == 5 * C  # neither swept again
    assert len(st._depths) == 3 and sorted(st._archive) == [frames[0].index, frames[1].index]
    fresh = S.RigStereo(rig, camera_overlap(rig, stride=8))
    for (d, c), f, exact in (((d2, c2), frames[2], True), ((d0, c0), frames[0], False)):
        fresh_d, fresh_c = fresh.depth(f.index, f.images)
        for a, b, ca, cb, spec in zip(d, fresh_d, c, fresh_c, rig.cameras):
            assert a.shape == (spec.height, spec.width) and a.dtype == np.float32 and (a > 0).mean() > 0.1
            if exact:
                np.testing.assert_array_equal(a, b)
                np.testing.assert_array_equal(ca, cb)
            else:
                assert np.array_equal(a > 0, b > 0) and not np.array_equal(a, b)  # rounded, nothing lost
                np.testing.assert_allclose(a, b, rtol=2**-11, atol=0)
                np.testing.assert_allclose(ca, cb, rtol=2**-11, atol=2**-25)


def test_depth_source_choice(synthetic_seq, tmp_path):
    """auto = sensor depth when every camera has it (exact or, per metadata.yaml, an
    inexact prior), else stereo when cameras overlap, else none; impossible choices and
    depth on some cameras only are clear errors, never a silent switch."""
    import shutil

    from mcgs_warp.data import open_sequence
    from mcgs_warp.data.sequence import CameraSubset
    from mcgs_warp.errors import InputError

    stereo = object()
    exact = choose_prior(synthetic_seq, "auto", lambda: stereo)
    assert isinstance(exact, SensorDepth) and exact.exact and exact.metric
    assert isinstance(choose_prior(synthetic_seq, "stereo", lambda: stereo), StereoDepth)
    assert isinstance(choose_prior(synthetic_seq, "none", lambda: stereo), NoDepth)
    mono = tmp_path / "mono"
    shutil.copytree(synthetic_seq.root, mono)
    (mono / "metadata.yaml").write_text("depth: mono\n")
    prior = choose_prior(open_sequence(mono), "auto", lambda: stereo)
    assert isinstance(prior, SensorDepth) and prior.metric and not prior.exact
    (mono / "metadata.yaml").write_text("depth: lidar\n")
    with pytest.raises(InputError, match="metadata.yaml: depth: expected one of exact | mono | none"):
        open_sequence(mono)
    none = tmp_path / "none"
    shutil.copytree(synthetic_seq.root, none)
    shutil.rmtree(none / "cam1" / "depth")
    partial = open_sequence(none)
    with pytest.raises(InputError, match="depth for some cameras only"):
        choose_prior(partial, "auto", lambda: stereo)
    with pytest.raises(InputError, match="no depth for camera"):
        choose_prior(partial, "sensor", lambda: stereo)
    for c in (0, 2):
        shutil.rmtree(none / f"cam{c}" / "depth")
    with pytest.raises(InputError, match="metadata.yaml: depth: says exact, but no cam<i>/depth folder"):
        open_sequence(none)
    (none / "metadata.yaml").write_text("depth: none\n")
    rgb_only = open_sequence(none)
    assert isinstance(choose_prior(rgb_only, "auto", lambda: stereo), StereoDepth)
    assert isinstance(choose_prior(CameraSubset(rgb_only, [1]), "auto", lambda: None), NoDepth)
    with pytest.raises(InputError, match="no two cameras of the rig overlap"):
        choose_prior(rgb_only, "stereo", lambda: None)


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
    from mcgs_warp.ba.edges import sliding_window

    assert sliding_window(3, 8) == [0, 1, 2]
    assert sliding_window(12, 8) == list(range(4, 12))
    assert sliding_window(0, 8) == []


def _errors(targets, weights, gt_t, gt_w):
    """Grid-pixel errors where both the estimate and the truth have a correspondence."""
    ok = (weights > 0.3) & (gt_w > 0)
    return np.linalg.norm(targets - gt_t, axis=-1)[ok], ok.sum() / max((gt_w > 0).sum(), 1)


def test_cross_view_matches_against_ground_truth(synthetic_seq):
    """Cross-view edges (front <-> fisheye left / pinhole right, yawed 80 deg): the sweep
    stereo's matches are accurate where confident, and far better than plain DIS there."""
    from mcgs_warp.frontend.flow import DISFlow, StereoMatches
    from mcgs_warp.frontend.stereo import RigStereo
    from problems import Problem

    P = Problem(synthetic_seq, [0, 4], temporal=False)
    cross = P.edges[P.edges[:, 0] == P.edges[:, 2]]
    assert len(cross) >= 4
    stereo = RigStereo(synthetic_seq.rig, camera_overlap(synthetic_seq.rig))
    t, w = StereoMatches(stereo).correspondences(P.buf, cross)
    gt_t, gt_w = P.targets[: len(cross)], P.weights[: len(cross)]
    assert np.array_equal(P.edges[: len(cross)], cross)
    err, cover = _errors(t, w, gt_t, gt_w)
    assert cover > 0.3, cover  # of the truly shared pixels
    assert np.median(err) < 0.05, np.median(err)  # grid px (x8 at full resolution)
    assert np.percentile(err, 90) < 0.3, np.percentile(err, 90)
    dis_t, dis_w = DISFlow().correspondences(P.buf, cross)
    dis_err = np.linalg.norm(dis_t - gt_t, axis=-1)[(dis_w > 0.3) & (gt_w > 0)]
    assert np.median(err) < 0.5 * np.median(dis_err), (np.median(err), np.median(dis_err))


def test_guided_flow_follows_the_geometry(synthetic_seq):
    """Temporal and cross-camera-time edges re-estimated from the current reprojection
    (depth and poses off by a few per cent / cm) land closer to the truth than raw DIS,
    and at least twice as close as the prediction they started from."""
    from mcgs_warp.frontend.flow import DISFlow, GuidedDIS
    from problems import Problem

    P = Problem(synthetic_seq, [0, 2, 4], cross_view=False)
    P.perturb(np.random.default_rng(3), trans=0.02, rot_deg=0.5, depth_noise=0.05)
    edges = np.array([e for e in P.edges if abs(e[0] - e[2]) == 2] + [[0, 0, 2, 1, 2], [2, 0, 0, 2, 2]], dtype=np.int32)
    gt_t, gt_w = P.targets_for(edges)
    # the geometric confidence alone (the photometric factor has its own test below)
    g_t, g_w = GuidedDIS(DISFlow()).correspondences(P.buf, edges, photometric=False)
    d_t, d_w = DISFlow().correspondences(P.buf, edges)
    g_err, g_cover = _errors(g_t, g_w, gt_t, gt_w)
    d_err, _ = _errors(d_t, d_w, gt_t, gt_w)
    assert g_cover > 0.5, g_cover
    assert np.median(g_err) < 0.1, np.median(g_err)
    assert np.mean(g_err) < np.mean(d_err), (np.mean(g_err), np.mean(d_err))
    # the prediction the guided flow started from (the current depths and poses), on the grid
    from mcgs_warp.frontend.flow import project_grid_depth, to_reduced

    p_err = []
    for e, (i, ci, j, cj) in enumerate(edges[:, :4]):
        T = np.linalg.inv(P.buf.get_poses()[j] @ synthetic_seq.rig.cameras[cj].T_b_c) @ P.buf.get_poses()[i] @ synthetic_seq.rig.cameras[ci].T_b_c
        z = P.buf.depth(i)[ci]
        p, inside, _ = project_grid_depth(P.buf, ci, z, T, cj)
        pred = to_reduced(p, 8).reshape(z.shape + (2,))
        ok = inside.reshape(z.shape) & (gt_w[e] > 0) & (g_w[e] > 0.3)
        p_err.append(np.linalg.norm(pred - gt_t[e], axis=-1)[ok])
    assert np.median(g_err) < 0.5 * np.median(np.concatenate(p_err)), (np.median(g_err), np.median(np.concatenate(p_err)))


def test_guided_flow_threads_match_one_thread(synthetic_seq, monkeypatch):
    """GuidedDIS matches its edges on several threads (one DIS each, OpenCV single-threaded
    meanwhile): the result equals one thread's bit for bit, and OpenCV's thread count is
    restored afterwards. A DISFlow subclass keeps its own flow on every thread; a flow
    object that cannot copy itself runs on one thread."""
    import cv2

    from mcgs_warp.frontend.flow import DISFlow, GuidedDIS
    from problems import Problem

    class Shifted(DISFlow):  # a subclass: every thread's copy must be one too
        def flow(self, image_a, image_b):
            f, conf = super().flow(image_a, image_b)
            return f + 0.5, conf

    class Wrapped:  # any object with flow(a, b) may replace DIS: it gets one thread
        def __init__(self):
            self.inner = DISFlow()

        def flow(self, image_a, image_b):
            return self.inner.flow(image_a, image_b)

    P = Problem(synthetic_seq, [0, 2, 4], cross_view=True)
    P.perturb(np.random.default_rng(5), trans=0.02, rot_deg=0.5, depth_noise=0.05)
    edges = P.edges[:7]  # more edges than threads, not a multiple of them
    threads = cv2.getNumThreads()
    serial = {}
    for make in (DISFlow, Shifted, Wrapped):
        results = {}
        for n in ("3", "1"):  # threads first: on a fresh buffer (its full-resolution rays not made yet)
            monkeypatch.setenv("MCGS_WARP_CPU_THREADS", n)
            results[n] = GuidedDIS(make()).correspondences(P.buf, edges)
            assert cv2.getNumThreads() == threads
        assert np.array_equal(results["1"][0], results["3"][0]) and np.array_equal(results["1"][1], results["3"][1]), make
        serial[make] = results["1"]
    assert (serial[DISFlow][1] > 0.5).mean() > 0.3  # real matches, not empty maps
    assert all(not np.array_equal(serial[Shifted][0][e], serial[DISFlow][0][e]) for e in range(len(edges)))  # every edge shifted
    assert np.array_equal(serial[Wrapped][0], serial[DISFlow][0])


def test_new_edges_fall_back_to_plain_dis_when_the_prediction_cannot_guide(synthetic_seq):
    """GuidedOrRaw: with a good pose guess new edges are the guided ones; when the guess is
    far off (keyframe 1 turned by 60 deg, as after a sudden turn under constant velocity) the
    prediction leaves the other view and those edges come from plain DIS instead."""
    from mcgs_warp.frontend.flow import DISFlow, GuidedDIS, GuidedOrRaw
    from mcgs_warp.geometry import se3_exp
    from problems import Problem

    P = Problem(synthetic_seq, [0, 2], cross_view=False)
    edges = P.edges[P.edges[:, 0] != P.edges[:, 2]]
    guided, raw = GuidedDIS(DISFlow()), DISFlow()
    both = GuidedOrRaw(guided, raw)
    t, w = both.correspondences(P.buf, edges)
    g_t, g_w = guided.correspondences(P.buf, edges)
    np.testing.assert_array_equal(t, g_t)
    np.testing.assert_array_equal(w, g_w)
    T = P.buf.get_poses()
    T[1] = T[1] @ se3_exp(np.array([0.0, 0.0, 0.0, 0.0, np.radians(60.0), 0.0]))
    P.buf.set_poses(T)
    t, w = both.correspondences(P.buf, edges)
    g_t, g_w = guided.correspondences(P.buf, edges)
    r_t, r_w = raw.correspondences(P.buf, edges)
    poor = (guided.correspondences(P.buf, edges, photometric=False)[1] > 0.5).mean(axis=(1, 2)) < 0.25
    assert poor.sum() >= len(edges) // 2
    np.testing.assert_array_equal(t[poor], r_t[poor])
    np.testing.assert_array_equal(w[~poor], g_w[~poor])
    gt_t, gt_w = P.targets_for(edges)
    err, cover = _errors(t, w, gt_t, gt_w)
    assert cover > 0.5 and np.median(err) < 0.1, (cover, np.median(err))


def test_guided_upsampling_keeps_depth_edges_where_the_image_has_them():
    """A near square (2 m, bright) in front of a far wall (20 m, dark) whose border does
    not fall on the stride-8 grid: bilinear interpolation of the grid samples spreads the
    edge over a cell, the image-guided upsampling keeps it at the image edge; a constant
    depth comes back exactly, and pixels with no known sample near them get 0."""
    spec = CameraSpec("c", "pinhole", 96, 64, (80.0, 80.0, 47.5, 31.5))
    v, u = np.mgrid[0:64, 0:96]
    near = (u >= 29) & (u < 67) & (v >= 19) & (v < 45)
    depth = np.where(near, 2.0, 20.0)
    image = np.repeat(np.where(near, 0.8, 0.2)[..., None], 3, -1).astype(np.float32)
    disp = (1.0 / depth[4::8, 4::8]).astype(np.float32)
    bilinear, _ = upsample_inverse_depth(disp, spec, 8)
    guided = upsample_inverse_depth_guided(disp, spec, 8, image)
    err_b, err_g = np.abs(bilinear - depth).mean(), np.abs(guided - depth).mean()
    assert err_g < 0.25 * err_b, (err_g, err_b)
    assert np.abs(guided - depth)[near].max() < 0.05 and np.median(np.abs(guided - depth)[~near]) < 1e-3

    flat = upsample_inverse_depth_guided(np.full((8, 12), 0.25, np.float32), spec, 8, image)
    np.testing.assert_allclose(flat, 4.0, rtol=1e-6)
    # a thin bright pole on a dark wall, between grid samples: no sample shares its colour,
    # yet every pixel of it still gets a depth (the colour weights are tiny, never zero)
    pole = np.full((64, 96, 3), 0.1, np.float32)
    pole[:, 41:43] = 0.9
    thin = upsample_inverse_depth_guided(np.full((8, 12), 0.25, np.float32), spec, 8, pole)
    np.testing.assert_allclose(thin, 4.0, rtol=1e-5)
    holes = np.full((8, 12), 0.25, np.float32)
    holes[:, 6:] = 0.0  # right half unknown
    part = upsample_inverse_depth_guided(holes, spec, 8, image)
    assert (part[:, :48] > 0).all() and (part[:, 64:] == 0).all()


def _guided_upsampling_numpy(disp, spec, stride, image, sigma_color=0.1, radius=1, sigma_space=0.5):
    """The joint bilateral upsampling written out in NumPy (float64): the kernel's reference."""
    H, W = spec.height, spec.width
    h, w = disp.shape
    o = stride // 2
    v, u = np.mgrid[0:H, 0:W]
    gu, gv = (u - o) / stride, (v - o) / stride
    cu, cv = np.floor(gu).astype(int), np.floor(gv).astype(int)
    img = np.asarray(image, np.float64)
    num, den = np.zeros((H, W)), np.zeros((H, W))
    for dv in range(-radius + 1, radius + 1):
        for du in range(-radius + 1, radius + 1):
            qu, qv = cu + du, cv + dv
            ok = (qu >= 0) & (qu < w) & (qv >= 0) & (qv < h)
            qu_c, qv_c = np.clip(qu, 0, w - 1), np.clip(qv, 0, h - 1)
            d = disp[qv_c, qu_c].astype(np.float64)
            ok &= d > 0
            col = img[np.minimum(qv_c * stride + o, H - 1), np.minimum(qu_c * stride + o, W - 1)]
            arg = -0.5 * ((gu - qu) ** 2 + (gv - qv) ** 2) / sigma_space**2 - 0.5 * ((img - col) ** 2).sum(-1) / sigma_color**2
            wgt = np.where(ok, np.exp(arg), 0.0)
            num += wgt * d
            den += wgt
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(den > 0, num / den, 0.0)
    return np.where(inv > 0, 1.0 / np.maximum(inv, 1e-9), 0.0)


@pytest.mark.parametrize("radius,stride", [(1, 8), (2, 4)])
def test_guided_upsampling_kernel_equals_numpy(radius, stride):
    """The Warp kernel against the NumPy formula: random inverse depths with holes, a random
    image (colour mismatches up to 1.7: float64 weights), sizes no multiple of the stride."""
    rng = np.random.default_rng(radius)
    spec = CameraSpec("c", "pinhole", 61, 45, (50.0, 50.0, 30.0, 22.0))
    disp = rng.uniform(0.05, 1.0, (45 // stride, 61 // stride)).astype(np.float32)
    disp[rng.random(disp.shape) < 0.3] = 0.0
    disp[:, (2 * disp.shape[1]) // 3 :] = 0.0  # wider than a pixel's reach: no depth there
    image = rng.random((45, 61, 3)).astype(np.float32)
    got = upsample_inverse_depth_guided(disp, spec, stride, image, radius=radius)
    want = _guided_upsampling_numpy(disp, spec, stride, image, radius=radius)
    assert ((got > 0) == (want > 0)).all() and (want > 0).mean() > 0.4 and (want == 0).any()
    np.testing.assert_allclose(got, want, rtol=2e-6)
    with pytest.raises(ValueError, match=r"image must be RGB \[45,61,3\]"):
        upsample_inverse_depth_guided(disp, spec, stride, image[:, :, 0])


def test_buffer_full_rays_are_each_cameras_pixel_rays(synthetic_seq):
    """One [C,H,W] ray array (the mapping loss's and the guided flow's) equals each camera's
    own unit-depth rays, also through the [c][:h,:w] view the guided flow takes; for pinhole
    cameras OpenCV projects each ray back onto its pixel."""
    from mcgs_warp.buffer import KeyframeBuffer
    from mcgs_warp.kernels.sweep import camera_rays

    buf = KeyframeBuffer(synthetic_seq.rig, stride=8, capacity=2)
    assert buf.full_rays is buf.full_rays  # made once
    checked = False
    for c, spec in enumerate(synthetic_seq.rig.cameras):
        own = camera_rays(spec.warp_camera(), buf.device).numpy()
        np.testing.assert_array_equal(buf.full_rays[c][: spec.height, : spec.width].numpy(), own)
        if spec.model == "pinhole":  # OpenCV projects each ray back onto its pixel
            import cv2

            fx, fy, cx, cy = spec.intrinsics
            K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)
            uv, _ = cv2.projectPoints(own.reshape(-1, 3).astype(np.float64), np.zeros(3), np.zeros(3), K, np.array(spec.distortion, np.float64))
            v, u = np.mgrid[0 : spec.height, 0 : spec.width]
            np.testing.assert_allclose(uv.reshape(spec.height, spec.width, 2), np.stack([u, v], -1), atol=1e-2)
            checked = True
    assert checked, "the synthetic rig has a pinhole camera"


def test_reduced_grid_coordinates_round_trip(synthetic_seq):
    """from_reduced inverts to_reduced, and the grid's own pixels are reduced pixels 0..w-1."""
    from mcgs_warp.buffer import grid_pixels
    from mcgs_warp.frontend.flow import from_reduced, to_reduced

    uv = grid_pixels(synthetic_seq.rig.cameras[0], 8)
    r = to_reduced(uv, 8)
    np.testing.assert_array_equal(r[0, :3, 0], [0, 1, 2])
    np.testing.assert_array_equal(from_reduced(r, 8), uv)


def test_guided_confidence_drops_matches_that_only_agree_with_a_wrong_prediction(synthetic_seq):
    """With depths far off (30 % noise per grid pixel) DIS cannot correct every prediction,
    and the forward-backward check passes what it left in place. The photometric factor
    of the confidence keeps fewer such matches: the confident matches are closer to the
    truth with it than without it (photo_sigma = inf: 10 % of them > 4 px off, 5 % with
    it); with depths this poor it keeps 20-45 % of the view confident (without: 90 %; the
    figures depend a little on OpenCV's version and thread count, and on the texture: the
    ray caster's floor fix took the ratio from 0.46 to 0.53)."""
    from mcgs_warp.frontend.flow import DISFlow, GuidedDIS

    P = Problem(synthetic_seq, [0, 2], cross_view=False)
    P.perturb(np.random.default_rng(4), trans=0.0, rot_deg=0.0, depth_noise=0.3, fixed=(0, 1))
    edges = P.edges[P.edges[:, 0] != P.edges[:, 2]]
    gt_t, gt_w = P.targets_for(edges)
    with_photo = GuidedDIS(DISFlow()).correspondences(P.buf, edges)
    without = GuidedDIS(DISFlow(), photo_sigma=np.inf).correspondences(P.buf, edges)
    (e1, c1), (e0, c0) = _errors(*with_photo, gt_t, gt_w), _errors(*without, gt_t, gt_w)
    assert np.mean(e1 > 0.5) < 0.6 * np.mean(e0 > 0.5), (np.mean(e1 > 0.5), np.mean(e0 > 0.5))
    assert c1 > 0.2 and c0 > 0.8, (c1, c0)


def test_image_motion_finds_a_pause_and_only_the_pause(tmp_path):
    """The keyframe test's flows say whether the rig moved since the frame before: on an
    indoor drive with camera noise, blur and JPEG (seed 3: 1 m/s, then standing still for 5
    frames) the frames of the pause are still and every frame of the drive moved, including
    those a mean-flow-magnitude rule would call still (turning while driving)."""
    from mcgs_warp.data.indoor import indoor_layout
    from mcgs_warp.data.synthetic import generate
    from mcgs_warp.system.trajectory_filler import STILL_MOTION

    lay = indoor_layout(3)
    seq = generate(tmp_path / "seq", n_cameras=2, n_frames=lay.pause_start + lay.pause_frames + 3, seed=3, progress=False, depth="none", scene="indoor", realism="camera")
    sel = KeyframeSelector(DISFlow(), seq.rig.cameras)
    last, motions = seq[0].images, {}
    for k in range(1, len(seq)):
        images = seq[k].images
        is_kf, motions[k] = sel.is_keyframe(last, images)
        if is_kf:
            last = images
    still = {k for k in motions if motions[k] < STILL_MOTION}
    true_steps = np.linalg.norm(np.diff(seq.groundtruth.positions, axis=0), axis=1)
    pause = {k for k in motions if true_steps[k - 1] < 1e-9}  # the same pose as the frame before
    assert len(pause) == lay.pause_frames
    assert still == pause, (sorted(still), sorted(pause), {k: round(v, 4) for k, v in motions.items()})


def test_keyframe_buffer_grows_with_its_keyframes(synthetic_seq):
    """The buffer starts with a few slots and doubles when a keyframe needs more: every
    keyframe's pose, depth, prior, confidence, JDSA grid and exposure survive the growth, and
    new slots take the defaults (no prior confidence 1, scales 1)."""
    from mcgs_warp.buffer import KeyframeBuffer
    from mcgs_warp.geometry import se3_exp

    rng = np.random.default_rng(0)
    buf = KeyframeBuffer(synthetic_seq.rig, stride=8, capacity=2)
    C, h, w = len(synthetic_seq.rig), buf.h, buf.w
    kept = []
    for k in range(5):
        T = se3_exp(rng.normal(size=6) * 0.1)
        disp, prior, conf = rng.uniform(0.1, 1, (C, h, w)), rng.uniform(1, 9, (C, h, w)), rng.uniform(0, 1, (C, h, w))
        assert buf.add(k, 0.1 * k, [None] * C, T, disp, depth_prior=prior, prior_conf=conf) == k
        grids = buf.scales.numpy()
        grids[k] = 1.0 + k
        buf.scales.assign(grids)
        e = buf.exposure.numpy()
        e[k] = k
        buf.exposure.assign(e)
        kept.append((T, disp, prior, conf))
    assert len(buf) == 5 and buf.capacity == 8
    np.testing.assert_allclose(buf.get_poses(), np.stack([t[0] for t in kept]), atol=1e-6)
    for k, (_, disp, prior, conf) in enumerate(kept):
        np.testing.assert_allclose(buf.disp.numpy()[k], disp, rtol=1e-6)
        np.testing.assert_allclose(buf.depth_prior.numpy()[k], prior, rtol=1e-6)
        np.testing.assert_allclose(buf.prior_conf.numpy()[k], conf, rtol=1e-6)
        assert (buf.scales.numpy()[k] == 1.0 + k).all() and (buf.exposure.numpy()[k] == k).all()
    assert (buf.prior_conf.numpy()[5:] == 1).all() and (buf.scales.numpy()[5:] == 1).all() and (buf.disp.numpy()[5:] == 0).all()


def test_keyframe_buffer_keeps_8_bit_images_compact():
    """Images read from 8-bit files (every value n / 255) are kept as uint8, a quarter of the
    memory, and read back as the same float32 bit for bit; any other image (resampled, edited,
    NaN) is kept exactly as given."""
    from mcgs_warp.buffer import compact_image, float_image

    rng = np.random.default_rng(0)
    eight_bit = rng.integers(0, 256, (6, 7, 3), dtype=np.uint8).astype(np.float32) / 255.0
    stored = compact_image(eight_bit)
    assert stored.dtype == np.uint8 and stored.nbytes * 4 == eight_bit.nbytes
    assert float_image(stored).dtype == np.float32 and np.array_equal(float_image(stored).view(np.uint32), eight_bit.view(np.uint32))
    resampled = eight_bit.copy()
    resampled[2, 3, 1] += 0.5 / 255.0  # between two 8-bit levels
    with_nan = eight_bit.copy()
    with_nan[0, 0, 0] = np.nan
    for image in (resampled, with_nan, rng.uniform(0, 1, (4, 5, 3)).astype(np.float32)):
        kept = compact_image(image)
        assert kept.dtype == np.float32 and np.array_equal(kept, image, equal_nan=True)
    assert compact_image(None) is None and float_image(None) is None
