"""Sweep stereo (kernels/sweep.py through mcgs_warp.frontend.stereo), its propagation and refinement (kernels/propagation.py, kernels/refine.py) against ray-cast depth,
for every camera model as the reference view, without rectification."""

import numpy as np
import pytest

from mcgs_warp.data.synthetic import SceneRenderer, build_scene
from mcgs_warp.frontend.stereo import RigStereo, StereoConfig, upsample_nearest
from mcgs_warp.geometry import pose, yaw_pitch_roll
from mcgs_warp.rig import CameraSpec, Rig
from warp_devices import devices

# OpenCV optical frame (x right, y down, z forward) looking along body +x (world x forward, z up).
Q_FORWARD = (-0.5, 0.5, -0.5, 0.5)

MODELS = {
    "pinhole": ("pinhole", 320, 240, (180.0, 180.0, 159.5, 119.5), (-0.05, 0.01, 0.001, -0.001, 0.0)),
    "fisheye": ("fisheye", 320, 240, (120.0, 120.0, 159.5, 119.5), (0.02, -0.01, 0.0, 0.0)),
    "equirectangular": ("equirectangular", 1024, 512, None, ()),  # 0.35 deg per pixel
}


def two_camera_rig(model: str, baseline: float = 0.3) -> Rig:
    """Reference camera of ``model`` and a pinhole ``baseline`` m to its left, both facing forward."""
    m, w, h, K, dist = MODELS[model]
    ref = CameraSpec("ref", m, w, h, K, dist, pose((0.2, 0.0, 0.0), Q_FORWARD))
    src = CameraSpec("src", "pinhole", 320, 240, (160.0, 160.0, 159.5, 119.5), (), pose((0.2, baseline, 0.0), Q_FORWARD))
    return Rig([ref, src])


def render(rig, T_w_b):
    r = SceneRenderer(build_scene(3), rig, supersample=2)
    color, depth = r.render(T_w_b)
    return [color[i, : c.height, : c.width] for i, c in enumerate(rig.cameras)], [depth[i, : c.height, : c.width] for i, c in enumerate(rig.cameras)]


@pytest.mark.parametrize("model", list(MODELS))
def test_sweep_matches_raycast_depth_for_each_camera_model(model):
    rig = two_camera_rig(model, baseline=0.4)
    T_w_b = np.eye(4)
    T_w_b[:3, :3] = yaw_pitch_roll(0.9)  # towards the left wall: depths of 2-8 m
    T_w_b[:3, 3] = (4.0, 0.3, 1.4)
    images, depths = render(rig, T_w_b)
    stereo = RigStereo(rig, np.ones((2, 2)), StereoConfig(far=60.0))
    assert stereo.pairs == [(0, 1), (1, 0)]
    est, conf = stereo.depth(0, images)
    d, gt = est[0], depths[0]
    ok = (conf[0] > 0) & (gt > 0)
    rel = np.abs(d[ok] - gt[ok]) / gt[ok]
    # The source sees only part of a fisheye's / equirectangular view: judge coverage
    # inside what it can see.
    assert ok.mean() > {"pinhole": 0.25, "fisheye": 0.05, "equirectangular": 0.02}[model], ok.mean()
    assert np.median(rel) <= 0.03, np.median(rel)
    assert (rel > 0.2).mean() < 0.08, (rel > 0.2).mean()


def test_textureless_views_give_no_confident_depth():
    rig = two_camera_rig("pinhole")
    flat = [np.full((c.height, c.width, 3), 0.5, np.float32) for c in rig.cameras]
    _, conf = RigStereo(rig, np.ones((2, 2))).depth(0, flat)
    assert conf[0].max() == 0.0 and conf[1].max() == 0.0


def test_left_right_check_removes_mismatches():
    """Without the check some confident pixels are wrong (occlusions, repetitive texture);
    with it the share of gross errors (off by half the depth) among them falls."""
    rig = two_camera_rig("pinhole", baseline=0.4)
    T_w_b = np.eye(4)
    T_w_b[:3, :3] = yaw_pitch_roll(0.5)
    T_w_b[:3, 3] = (6.0, -0.5, 1.4)
    images, depths = render(rig, T_w_b)

    def gross(lr_px):
        est, conf = RigStereo(rig, np.ones((2, 2)), StereoConfig(lr_px=lr_px)).depth(0, images)
        ok = (conf[0] > 0) & (depths[0] > 0)
        return (np.abs(est[0][ok] - depths[0][ok]) > 0.5 * depths[0][ok]).mean()

    checked, unchecked = gross(1.0), gross(1e9)
    assert checked < 0.5 * unchecked, (checked, unchecked)


def test_temporal_sources_measure_the_far_scene_the_rig_baseline_cannot():
    """A 0.1 m rig pair resolves the far end of the room poorly; sweeping the same view
    against the camera 2 m further back (the rig's own travel, at known poses) measures it,
    and the rig pair's depth stays where the time sweep has none."""
    rig = two_camera_rig("pinhole", baseline=0.1)
    T_w_b = np.eye(4)
    T_w_b[:3, :3] = yaw_pitch_roll(0.15)  # down the room: far pixels at 8-25 m
    T_w_b[:3, 3] = (3.0, 0.0, 1.4)
    T_back = T_w_b.copy()
    T_back[:3, 3] = (1.0, -0.4, 1.4)  # 2 m of travel back, a little to the side
    images, depths = render(rig, T_w_b)
    back, _ = render(rig, T_back)
    stereo = RigStereo(rig, np.ones((2, 2)), StereoConfig(far=60.0))
    spec = rig.cameras[0]
    T_src_ref = np.linalg.inv(T_back @ spec.T_b_c) @ (T_w_b @ spec.T_b_c)
    s = stereo.cfg.scale
    rig_d, rig_c = stereo.depth(0, images)
    t_d = upsample_nearest(stereo.temporal_depth(0, images, [[(back[0], T_src_ref)], []])[0], spec, s)
    t_c = (t_d > 0).astype(np.float32)
    gt = depths[0]

    far = gt > 8.0

    def error(d, c, mask):
        ok = (c > 0) & mask
        return np.median(np.abs(d[ok] - gt[ok]) / gt[ok]), ok.sum()

    rig_err, _ = error(rig_d[0], rig_c[0], far)
    t_err, _ = error(t_d, t_c, far)
    assert t_err < 0.8 * rig_err, (t_err, rig_err)
    temporal = t_d != rig_d[0]  # where the temporal sweep won
    won_err, won_n = error(t_d, t_c, far & temporal)
    assert won_n > 0.2 * far.sum() and won_err < 0.1, (won_n, won_err)
    assert error(rig_d[0], rig_c[0], far & temporal & (rig_c[0] > 0))[0] > 1.5 * won_err
    alone = upsample_nearest(stereo.time_sweep(0, images[0], [(back[0], T_src_ref)])[0], spec, s)
    behind = (alone <= 0) & (rig_d[0] > 0)  # the time sweep has none there: the rig pair's depth
    assert behind.sum() > 0 and np.array_equal(t_d[behind], rig_d[0][behind])
    assert np.array_equal(t_d[alone > 0], alone[alone > 0])


def grid_like(depth: np.ndarray, stride: int = 8, amplitude: float = 0.1) -> np.ndarray:
    """What MCBA hands the mapper: depth sampled every ``stride`` px, upsampled bilinearly in
    inverse depth (edges spread over a cell), times a smooth error field within
    ``1 +- amplitude``."""
    import cv2

    H, W = depth.shape
    inv = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-6), 0.0).astype(np.float32)
    up = cv2.resize(inv[stride // 2 :: stride, stride // 2 :: stride], (W, H), interpolation=cv2.INTER_LINEAR)
    field = cv2.resize(np.random.default_rng(0).uniform(1 - amplitude, 1 + amplitude, (4, 6)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
    return np.where(up > 0, field / np.maximum(up, 1e-6), 0.0).astype(np.float32)


def five_views(model: str):
    """A reference view of ``model`` and five source views at known poses (the rig's pinhole
    now, both cameras 0.6 m back and 0.3 m ahead), rendered with their ray-cast depth.
    Returns (rig, reference image, reference depth, sources as (image, depth, T_src_ref,
    camera index))."""
    rig = two_camera_rig(model, baseline=0.3)
    T_w_b = np.eye(4)
    T_w_b[:3, :3] = yaw_pitch_roll(0.9)
    T_w_b[:3, 3] = (4.0, 0.3, 1.4)
    images, depths = render(rig, T_w_b)
    ref_c = T_w_b @ rig.cameras[0].T_b_c
    sources = [(images[1], depths[1], np.linalg.inv(T_w_b @ rig.cameras[1].T_b_c) @ ref_c, 1)]
    for step in (-0.6, 0.3):
        T = T_w_b.copy()
        T[:3, 3] += T_w_b[:3, 0] * step
        other, d = render(rig, T)
        sources += [(other[c], d[c], np.linalg.inv(T @ rig.cameras[c].T_b_c) @ ref_c, c) for c in (0, 1)]
    return rig, images[0], depths[0], sources


@pytest.mark.parametrize("model", list(MODELS))
def test_propagation_moves_a_grid_depth_towards_the_raycast_depth(model):
    """One PatchMatch-style pass against five views at known poses (the rig pair now, both
    cameras 0.6 m back and 0.3 m ahead) takes a blurred, up to 10 %-off depth map closer to
    the ray-cast depth, for every camera model as the reference: the mean error falls by a
    fifth, the median relative error by half; an exact map stays nearly exact (median
    change below 0.5 %); pixels without depth stay without, and the pixels around a hole
    keep their depth."""
    from mcgs_warp.frontend.stereo import grey
    from mcgs_warp.kernels.sweep import camera_rays
    from mcgs_warp.kernels.propagation import propagate_depth

    rig, image, gt, sources = five_views(model)
    cams = [c.warp_camera() for c in rig.cameras]

    def propagate(depth):
        return propagate_depth(grey(image, 1), camera_rays(cams[0], "cpu"), depth, [grey(im, 1) for im, _d, _T, _c in sources], [cams[c] for *_x, c in sources], np.stack([T for _im, _d, T, _c in sources]))

    start = grid_like(gt)
    start[:20, :20] = 0.0  # unknown
    hole = np.zeros(gt.shape, bool)
    hole[gt.shape[0] // 2 : gt.shape[0] // 2 + 20, gt.shape[1] // 2 : gt.shape[1] // 2 + 30] = True
    start[hole] = 0.0
    out = propagate(start)
    assert out.shape == gt.shape and ((out > 0) == (start > 0)).all()
    # next to a hole the pixel's own depth cannot be scored (its window is not whole): it stays
    import cv2

    rim = (cv2.dilate(hole.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0) & ~hole
    assert (out[rim] == start[rim]).all()
    ok = (gt > 0) & (start > 0)
    before, after = np.abs(start - gt)[ok], np.abs(out - gt)[ok]
    assert after.mean() < 0.8 * before.mean(), (after.mean(), before.mean())
    assert np.median(after / gt[ok]) < 0.5 * np.median(before / gt[ok]), (np.median(after / gt[ok]), np.median(before / gt[ok]))
    exact = propagate(np.where(gt > 0, gt, 0.0).astype(np.float32))
    assert np.median(np.abs(exact - gt)[gt > 0] / gt[gt > 0]) < 0.005


def window_zncc_reference(ref, warped, r, min_std, min_valid):
    """float64 ``1 - ZNCC`` [H,W] of the direct (2r+1)^2 window of ``warped`` [H,W] against
    ``ref`` over the valid samples (``>= 0``); 3 (NO_COST) where fewer than ``min_valid`` of
    the in-image window is valid or either window is flat (sweep.zncc_cost's rule)."""
    H, W = ref.shape
    out = np.full((H, W), 3.0)
    for y in range(H):
        for x in range(W):
            a = ref[max(0, y - r) : y + r + 1, max(0, x - r) : x + r + 1].astype(np.float64)
            b = warped[max(0, y - r) : y + r + 1, max(0, x - r) : x + r + 1].astype(np.float64)
            ok = b >= 0
            n = ok.sum()
            if n < min_valid * a.size or n <= 1:
                continue
            a, b = a[ok], b[ok]
            va, vb = a.var(), b.var()
            if va > min_std**2 and vb > 0.25 * min_std**2:
                out[y, x] = 1.0 - np.clip(((a - a.mean()) * (b - b.mean())).mean() / np.sqrt(va * vb), -1, 1)
    return out


def test_sliding_window_zncc_equals_the_direct_window_sum():
    """The window ZNCC (zncc_cost_kernel) as the sweep uses it (3/4 of the window valid) and
    as the propagation does (all of it, the two lowest costs over sources fed one at a time),
    sliding its window down each column over bands of rows, equals a direct float64 sum over
    each pixel's window, image borders and invalid samples included."""
    import warp as wp

    from mcgs_warp.kernels.sweep import NO_COST, zncc_cost_kernel

    rng = np.random.default_rng(3)
    S, D, H, W, r = 3, 4, 23, 26, 2
    ref = rng.random((H, W)).astype(np.float32)
    ref[:6, :7] = 0.5  # a flat corner: no cost there
    warped = rng.random((S, D, H, W)).astype(np.float32)
    warped[rng.random((S, D, H, W)) < 0.02] = -1.0  # a few invalid samples
    warped[:, :, 15:, 20:] = -1.0  # and a block where the source ends
    sweep_ref = np.stack([[window_zncc_reference(ref, warped[s, k], r, 0.02, 0.75) for k in range(D)] for s in range(S)])
    prop_ref = np.stack([[window_zncc_reference(ref, warped[s, k], r, 0.02, 1.0) for k in range(D)] for s in range(S)])
    assert (sweep_ref < float(NO_COST)).mean() > 0.5 and (prop_ref < float(NO_COST)).mean() > 0.3
    assert ((sweep_ref < float(NO_COST)) & (prop_ref >= float(NO_COST))).any()  # the two rules differ here

    ref_w = wp.array(ref, dtype=float, device="cpu")
    cost = wp.empty((S * D, H, W), dtype=float, device="cpu")
    flat = wp.array(warped.reshape(S * D, H, W), dtype=float, device="cpu")
    for row0, rows in ((0, 5), (5, 1), (6, 17)):  # bands of rows, as run_row_bands launches them
        wp.launch(zncc_cost_kernel, dim=(S * D, W), inputs=[ref_w, flat, r, 0.02, 0.75, row0, rows, 0], outputs=[cost, cost], device="cpu")
    np.testing.assert_allclose(cost.numpy().reshape(S, D, H, W), sweep_ref, atol=2e-5)

    m1 = wp.full((D, H, W), NO_COST, dtype=float, device="cpu")
    m2 = wp.full((D, H, W), NO_COST, dtype=float, device="cpu")
    for s in range(S):
        one = wp.array(warped[s], dtype=float, device="cpu")
        for row0, rows in ((0, 11), (11, 12)):
            wp.launch(zncc_cost_kernel, dim=(D, W), inputs=[ref_w, one, r, 0.02, 1.0, row0, rows, 1], outputs=[m1, m2], device="cpu")
    srt = np.sort(prop_ref, axis=0)
    np.testing.assert_allclose(m1.numpy(), srt[0], atol=2e-5)
    np.testing.assert_allclose(m2.numpy(), srt[1], atol=2e-5)


@pytest.mark.parametrize("model", list(MODELS))
def test_consistency_drops_depths_the_other_views_do_not_confirm(model):
    """Five views at known poses with their ray-cast depth maps (the rig pair now, both
    cameras 0.6 m back and 0.3 m ahead): in a reference map with a patch pulled 30 % nearer
    and scattered pixels 40 % nearer, for every camera model as the reference, fewer than
    5 % of the wrong depths survive, while most exact depths do (those two sources see)."""
    from mcgs_warp.kernels.sweep import camera_rays
    from mcgs_warp.kernels.propagation import consistent_depth

    rig, _image, gt, sources = five_views(model)
    cams = [c.warp_camera() for c in rig.cameras]
    rays = [camera_rays(c, "cpu") for c in cams]

    def filtered(depth, sources=sources):
        return consistent_depth(rays[0], depth, [rays[c] for *_x, c in sources], [d for _im, d, _T, _c in sources], [cams[c] for *_x, c in sources], np.array([T for _im, _d, T, _c in sources]).reshape(-1, 4, 4))

    H, W = gt.shape
    wrong = np.zeros(gt.shape, bool)
    wrong[H // 3 : H // 3 + 30, W // 3 : W // 3 + 40] = True
    wrong |= np.random.default_rng(1).random(gt.shape) < 0.05
    wrong &= gt > 0
    start = np.where(wrong, gt * np.where(np.random.default_rng(2).random(gt.shape) < 0.5, 0.7, 0.6), gt).astype(np.float32)
    out = filtered(start)
    assert ((out == start) | (out == 0)).all()  # kept as it was, or dropped
    kept_wrong = (out[wrong] > 0).mean()
    kept_right = (out[(gt > 0) & ~wrong] > 0).mean()
    assert kept_wrong < 0.05, kept_wrong
    assert kept_right > 0.8, kept_right
    # fewer sources than min_views: judged by all there are (here the rig's pinhole alone, which
    # sees a part of a fisheye's or a panorama's view); none: kept as is
    one = filtered(start, sources[:1])
    assert (one[wrong] > 0).mean() < 0.05 and (one[(gt > 0) & ~wrong] > 0).mean() > 0.05  # 9 % for the panorama
    assert (filtered(start, []) == start).all()
    with pytest.raises(ValueError, match="expected one of each per source"):
        consistent_depth(rays[0], start, [rays[0]], [gt, gt], [cams[0]], np.eye(4)[None])


@pytest.mark.parametrize("model", list(MODELS))
def test_adaptive_rescoring_undoes_foreground_fattening(model):
    """A depth map whose nearer surfaces spill 3 px across every depth edge (what plain window
    matching leaves): with the reference's colours, re-scoring at depth edges with adaptive
    support weights takes back more of the spill than the plain pass does, for every camera
    model as the reference (a modest gain: about 6 % of the error left at the edges; the
    SLAM runs gain as much in rendered depth), and leaves pixels away from depth edges as the
    plain pass leaves them."""
    import cv2

    from mcgs_warp.frontend.stereo import grey
    from mcgs_warp.kernels.sweep import camera_rays
    from mcgs_warp.kernels.propagation import propagate_depth

    rig, image, gt, sources = five_views(model)
    cams = [c.warp_camera() for c in rig.cameras]
    rays = camera_rays(cams[0], "cpu")

    def propagate(depth, colour):
        return propagate_depth(grey(image, 1), rays, depth, [grey(im, 1) for im, _d, _T, _c in sources], [cams[c] for *_x, c in sources], np.stack([T for _im, _d, T, _c in sources]), ref_colour=colour)

    start = np.where(gt > 0, cv2.erode(np.where(gt > 0, gt, 1e9).astype(np.float32), np.ones((7, 7), np.uint8)), 0.0).astype(np.float32)
    box = np.ones((9, 9), np.uint8)
    edge = (gt > 0) & (cv2.dilate(gt, box) > 1.2 * cv2.erode(np.where(gt > 0, gt, 1e9).astype(np.float32), box))
    spill = edge & (start < 0.95 * gt)
    plain, adaptive = propagate(start, None), propagate(start, image)
    err = lambda d: np.abs(d - gt)[spill].mean()
    # pinhole / equirectangular: 1.15 -> 1.08 / 1.17 -> 1.09 m; the fisheye's wide view puts half
    # its pixels at depth edges (the floor at grazing angles), where the gain is smaller
    assert err(adaptive) < (0.99 if model == "fisheye" else 0.95) * err(plain), (err(adaptive), err(plain), err(start))
    with pytest.raises(ValueError, match="ref_colour must be a float RGB image"):
        propagate(start, image[:-1])
    with pytest.raises(ValueError, match="rescore must be 0"):
        propagate_depth(grey(image, 1), rays, start, [grey(sources[0][0], 1)], [cams[sources[0][3]]], sources[0][2][None], ref_colour=image, rescore=1)
    away = (cv2.dilate(start, box) <= 1.2 * cv2.erode(np.where(start > 0, start, 1e9).astype(np.float32), box)) & (start > 0)
    assert (adaptive[away] == plain[away]).all()


def _adaptive_cost_reference(ref, weights, rays, depth, src, cam, T, pixels, radius, min_std=0.005):
    """float64 ``1 - ZNCC`` of each pixel's adaptive window at its own depth against one source,
    every window sample projected exactly (kernels/reference.py) and sampled bilinearly; 3
    (NO_COST) where invalid samples carry over 0.1 % of the window's weight or a window is flat."""
    from mcgs_warp.kernels import reference

    Hs, Ws = src.shape
    out = []
    for y, x in pixels:
        w, a, b = [], [], []
        o = 0
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                wt = float(weights[y, x, o])
                o += 1
                if wt <= 0.0:
                    continue
                X = T[:3, :3] @ (rays[y + dy, x + dx].astype(np.float64) * depth[y, x]) + T[:3, 3]
                value = -1.0
                if reference.in_domain(cam, X[None])[0]:
                    u, v = reference.project(cam, X[None])[0]
                    if 0 <= u <= Ws - 1 and 0 <= v <= Hs - 1:
                        x0, y0 = min(int(u), Ws - 2), min(int(v), Hs - 2)
                        fu, fv = u - x0, v - y0
                        value = (src[y0, x0] * (1 - fu) + src[y0, x0 + 1] * fu) * (1 - fv) + (src[y0 + 1, x0] * (1 - fu) + src[y0 + 1, x0 + 1] * fu) * fv
                w.append(wt)
                a.append(float(ref[y + dy, x + dx]))
                b.append(value)
        w, a, b = np.array(w), np.array(a), np.array(b)
        ok = b >= 0
        if w[ok].sum() < 0.999 * w.sum():
            out.append(3.0)
            continue
        w, a, b = w[ok], a[ok], b[ok]
        n = w.sum()
        ma, mb = (w * a).sum() / n, (w * b).sum() / n
        va, vb = (w * a * a).sum() / n - ma * ma, (w * b * b).sum() / n - mb * mb
        if va > min_std**2 and vb > 0.25 * min_std**2:
            out.append(1.0 - np.clip(((w * a * b).sum() / n - ma * mb) / np.sqrt(va * vb), -1, 1))
        else:
            out.append(3.0)
    return np.array(out)


@pytest.mark.parametrize("model", list(MODELS))
def test_adaptive_window_cost_equals_exact_projection_of_every_sample(model):
    """The re-scoring's window follows its centre's local affine map into the source (one
    projection per window, not 81): its costs equal a float64 window whose every sample is
    projected exactly, for every camera model as the reference and each of the five sources
    (pinhole and the reference's model; an equirectangular source is projected per sample)."""
    import warp as wp

    from mcgs_warp.frontend.stereo import grey
    from mcgs_warp.kernels.camera import Camera
    from mcgs_warp.kernels.propagation import adaptive_window_kernel, depth_candidates, support_weights_kernel
    from mcgs_warp.kernels.sweep import camera_rays

    rig, image, gt, sources = five_views(model)
    cams = [c.warp_camera() for c in rig.cameras]
    rays = camera_rays(cams[0], "cpu")
    H, W = gt.shape
    r = 4
    ref = grey(image, 1).astype(np.float32)
    rng = np.random.default_rng(1)
    ys, xs = np.nonzero(gt[r:-r, r:-r] > 0)
    pick = rng.choice(len(ys), 150, replace=False)
    pixels = [(int(ys[i]) + r, int(xs[i]) + r) for i in pick]
    at = np.zeros((H, W), np.int32)
    picked = np.full((1, H, W), -1, np.int32)
    for y, x in pixels:
        at[y, x], picked[0, y, x] = 1, 0  # candidate 0: the pixel's own depth
    depth_w = wp.array(gt.astype(np.float32), dtype=float, device="cpu")
    ref_w = wp.array(ref, dtype=float, device="cpu")
    weights = wp.zeros((H, W, (2 * r + 1) ** 2), dtype=float, device="cpu")
    moments = wp.zeros((H, W), dtype=wp.vec3, device="cpu")
    colour = wp.array(np.ascontiguousarray(image, np.float32), dtype=wp.vec3, device="cpu")
    wp.launch(support_weights_kernel, dim=(H, W), inputs=[ref_w, colour, r, 0.1, 4.5, wp.array(at, dtype=wp.int32, device="cpu")], outputs=[weights, moments], device="cpu")
    cand = wp.array(depth_candidates(), dtype=wp.vec3, device="cpu")
    for im, _d, T, c in sources:
        src = grey(im, 1).astype(np.float32)
        a1 = wp.full((1, H, W), 3.0, dtype=float, device="cpu")
        a2 = wp.full((1, H, W), 3.0, dtype=float, device="cpu")
        inputs = [ref_w, weights, moments, rays, depth_w, cand, wp.array(picked, dtype=wp.int32, device="cpu"), wp.array(src[None], dtype=float, device="cpu"), wp.array([cams[c]], dtype=Camera, device="cpu"), wp.array([T.astype(np.float32)], dtype=wp.mat44, device="cpu"), 0, r, 0.005, 0]
        wp.launch(adaptive_window_kernel, dim=(1, H, W), inputs=inputs, outputs=[a1, a2], device="cpu")
        got = a1.numpy()[0][tuple(np.array(pixels).T)]
        want = _adaptive_cost_reference(ref, weights.numpy(), rays.numpy(), gt, src, cams[c], T, pixels, r)
        both = (got < 3.0) & (want < 3.0)
        assert both.sum() >= (10 if model == "equirectangular" else 30), (model, c, both.sum())  # the full sphere: most pixels leave the pinhole source
        assert (got < 3.0).sum() == pytest.approx((want < 3.0).sum(), abs=2), (model, c)  # a window on a source's rim may go either way
        err = np.abs(got - want)[both]
        # float32 rounding alone: median 4e-5, 95 % below 5e-4 (a local affine map: median 2.6e-3 on the fisheye)
        assert np.median(err) < 3e-4 and np.quantile(err, 0.95) < 1.5e-3 and err.max() < 1e-2, (model, c, np.median(err), np.quantile(err, 0.95), err.max())


def _patch_sad_reference(views, va, vb, uv_a, uv_b, radius):
    """float64 NumPy twin of kernels.refine.patch_sad (bilinear, border replicated)."""

    def sample(img, u, v):
        H, W = img.shape
        u, v = np.clip(np.nan_to_num(u), 0, W - 1), np.clip(np.nan_to_num(v), 0, H - 1)
        x0, y0 = np.minimum(u.astype(int), max(W - 2, 0)), np.minimum(v.astype(int), max(H - 2, 0))
        x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
        fx, fy = u - x0, v - y0
        return (img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy) + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy

    out = np.zeros(uv_a.shape[:3])
    for e in range(len(va)):
        a, b = views[va[e]].astype(np.float64), views[vb[e]].astype(np.float64)
        d = np.stack([sample(a, uv_a[e, ..., 0] + dx, uv_a[e, ..., 1] + dy) - sample(b, uv_b[e, ..., 0] + dx, uv_b[e, ..., 1] + dy) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)])
        out[e] = np.abs(d - d.mean(0)).mean(0)
    return out


@pytest.mark.parametrize("device", devices())
def test_patch_sad_matches_a_float64_twin(device):
    """Many matches between views of different sizes in one launch, near and beyond the
    borders (replicated) and with NaN targets, agree with a float64 NumPy twin."""
    from mcgs_warp.kernels.refine import patch_sad

    rng = np.random.default_rng(0)
    views = [rng.random((40, 50)).astype(np.float32), rng.random((30, 64)).astype(np.float32), rng.random((2, 3)).astype(np.float32)]
    va, vb = [0, 1, 2, 0], [1, 0, 0, 2]
    uv_a = rng.uniform(-5, 70, (4, 6, 7, 2)).astype(np.float32)
    uv_b = rng.uniform(-5, 70, (4, 6, 7, 2)).astype(np.float32)
    uv_b[1, 2, 3] = np.nan
    uv_a[2, 1, 1, 0] = np.nan  # one coordinate only
    for radius in (0, 1, 3):
        got = patch_sad(views, va, vb, uv_a, uv_b, radius=radius, device=device)
        np.testing.assert_allclose(got, _patch_sad_reference(views, va, vb, uv_a, uv_b, radius), atol=2e-6)
    with pytest.raises(ValueError, match="uv_a and uv_b"):
        patch_sad(views, va, vb, uv_a, uv_b[:3], device=device)
    with pytest.raises(ValueError, match="radius must be 0..3"):
        patch_sad(views, va, vb, uv_a, uv_b, radius=4, device=device)
    with pytest.raises(ValueError, match="view_b must index the 3 views"):
        patch_sad(views, va, [1, 0, 0, 3], uv_a, uv_b, device=device)


def test_patch_sad_equals_opencv_remap_patches():
    """The kernel reproduces what the flow front end computed before it, patches sampled by
    cv2.remap (bilinear, BORDER_REPLICATE), for fractional, integer, out-of-view and
    sentinel (-1e4) positions."""
    import cv2

    from mcgs_warp.kernels.refine import patch_sad

    rng = np.random.default_rng(3)
    a = cv2.GaussianBlur(rng.random((48, 64)).astype(np.float32), (0, 0), 1.0)
    b = cv2.GaussianBlur(rng.random((40, 70)).astype(np.float32), (0, 0), 1.0)
    uv_a = rng.uniform(-3, 66, (1, 5, 6, 2)).astype(np.float32)
    uv_b = rng.uniform(-3, 72, (1, 5, 6, 2)).astype(np.float32)
    uv_a[0, 0] = np.round(uv_a[0, 0])
    uv_b[0, 1, :2] = -1e4
    diffs = []
    for dy in range(-3, 4):
        for dx in range(-3, 4):
            pa = cv2.remap(a, uv_a[0, ..., 0] + dx, uv_a[0, ..., 1] + dy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            pb = cv2.remap(b, uv_b[0, ..., 0] + dx, uv_b[0, ..., 1] + dy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            diffs.append(pa - pb)
    d = np.stack(diffs)
    want = np.abs(d - d.mean(0)).mean(0)
    np.testing.assert_allclose(patch_sad([a, b], [0], [1], uv_a, uv_b)[0], want, atol=1e-6)


def test_patch_sad_is_zero_at_the_true_shift_only():
    """Zero where the patches show the same content (an image and its copy shifted by
    (5, 3) px, also 0.1 brighter), clearly above zero 2 px off."""
    import cv2

    from mcgs_warp.kernels.refine import patch_sad

    rng = np.random.default_rng(0)
    a = cv2.cvtColor(cv2.GaussianBlur(rng.random((60, 80, 3)).astype(np.float32), (0, 0), 1.5), cv2.COLOR_RGB2GRAY)
    b = np.roll(a, (3, 5), axis=(0, 1))
    v, u = np.mgrid[10:40:4, 10:60:4].astype(np.float32)
    uv = np.stack([u, v], -1)[None]
    assert patch_sad([a, b], [0], [1], uv, uv + [5, 3]).max() < 1e-5
    assert patch_sad([a, b + 0.1], [0], [1], uv, uv + [5, 3]).max() < 1e-5  # a brighter view: the same match
    wrong = patch_sad([a, b], [0], [1], uv, uv + [7, 3])
    assert wrong.min() > 0.005 and wrong.mean() > 0.02, (wrong.min(), wrong.mean())


@pytest.mark.parametrize("model", list(MODELS))
def test_point_refinement_sharpens_the_sweep_depth_at_full_resolution(model):
    """refine_points, started from the half-resolution sweep's depth at grid pixels (what
    the cross-view matches read), lands closer to the ray-cast depth without a bias; a
    start further off than its search range gets no depth."""
    from mcgs_warp.frontend.stereo import grey
    from mcgs_warp.kernels.sweep import camera_rays
    from mcgs_warp.kernels.refine import refine_points

    rig = two_camera_rig(model, baseline=0.4)
    T_w_b = np.eye(4)
    T_w_b[:3, :3] = yaw_pitch_roll(0.9)
    T_w_b[:3, 3] = (4.0, 0.3, 1.4)
    images, depths = render(rig, T_w_b)
    est, conf = RigStereo(rig, np.ones((2, 2)), StereoConfig(far=60.0)).depth(0, images)
    v, u = np.mgrid[4 : rig.cameras[0].height : 8, 4 : rig.cameras[0].width : 8]
    ok = (conf[0][v, u] > 0) & (depths[0][v, u] > 0)
    pix = np.stack([u[ok], v[ok]], 1)
    gt, z0 = depths[0][v, u][ok], est[0][v, u][ok]
    assert len(pix) > 40
    cams = [c.warp_camera() for c in rig.cameras]
    T = np.linalg.inv(rig.cameras[1].T_b_c) @ rig.cameras[0].T_b_c
    rays = camera_rays(cams[0], "cpu")

    def refine(rho0, count=12):
        return refine_points(grey(images[0], 1), rays, grey(images[1], 1), cams[1], T, pix, rho0, 0.25, count)[0]

    rho = refine(1.0 / z0)
    kept = rho > 0
    assert kept.mean() > 0.85, kept.mean()
    before = np.abs(z0 / gt - 1)
    after = np.abs(1.0 / rho[kept] / gt[kept] - 1)
    assert np.median(after) < 0.8 * np.median(before[kept]), (np.median(after), np.median(before[kept]))
    assert abs(np.median(1.0 / rho[kept] / gt[kept] - 1)) < 0.005
    # a start two steps past the range (count 2: +-0.5 px) has its best candidate at the end: no depth
    rho_gt = 1.0 / gt
    far_off = refine(rho_gt * 0.8, count=2)
    near_start = refine(rho_gt, count=2)
    assert (far_off == 0).mean() > 0.8 and (near_start > 0).mean() > 0.6
