"""Gaussian mapping: fitting quality, anchors, exposure, poses, densify/prune."""

import numpy as np
import warp as wp

from conftest import HELD_OUT, KEYFRAMES, make_mapper
from mcgs_warp.geometry import matrix_to_quat, quat_to_matrix, se3_exp
from mcgs_warp.kernels import Views, render
from mcgs_warp.mapping.gaussian_map import GaussianMap
from mcgs_warp.mapping.mapper import MappingConfig
from mcgs_warp.mapping.refine import exposure_gains, joint_refinement


def views_at(seq, frames):
    return [(seq.groundtruth.poses[f], seq[f].images) for f in frames]


def test_fit_reaches_target_psnr(fitted, mapping_seq):
    train = fitted.evaluate(views_at(mapping_seq, KEYFRAMES))
    held = fitted.evaluate(views_at(mapping_seq, HELD_OUT))
    # README ("Mapping"): about 31.0 dB on the training views after 150 iterations and the same
    # on held-out frames; 26.4 at the start. The bar leaves room for CUDA, whose atomic float32
    # gradient sums change Adam's path (30.0 vs 30.3 dB on the CPU at 100 iterations).
    assert train >= 30.3, train
    assert abs(held - train) < 0.5, (train, held)
    first = np.mean([r.psnr for r in fitted.history[:5]])
    assert fitted.history[-1].psnr > first + 2.0  # the optimizer does the work, not just the init


def test_step_matches_the_host_loss(fitted, mapping_seq):
    """A device-resident mapping step gives the loss, PSNR and exposure gradient of the
    former host loss on the same render (keyframe views made on the device as on the host)."""
    from loss_reference import keyframe_loss

    cfg = MappingConfig(lambda_scale=0.0, densify_every=0, lr_means=0, lr_log_scales=0, lr_quats=0, lr_opacity=0, lr_colors=0, lr_exposure=1e-3)
    m = make_mapper(mapping_seq, cfg, fitted.map.to_numpy())
    exposure = np.array([[0.05, 0.01], [-0.03, 0.02], [0.0, -0.01]], np.float32)
    e = m.buf.exposure.numpy()
    e[1] = exposure
    m.buf.exposure.assign(e)
    views = m.views(1)
    T_c_w = np.linalg.inv(m.buf.rig.camera_poses(m.buf.get_poses()[1]))
    np.testing.assert_allclose(views.viewmats.numpy(), T_c_w, atol=1e-5)
    out = render(m.map.gaussians, views)
    sizes = [(s.height, s.width) for s in m.buf.rig.cameras]
    rays = [m.full_rays(c) for c in range(len(sizes))]
    total, _, _, grad_exposure, psnr = keyframe_loss(
        out.color.numpy(), out.depth.numpy(), sizes, m.buf.keyframe_images(1), m.buf.targets[1], rays, exposure.astype(np.float64), cfg.lambda_ssim, cfg.lambda_depth, cfg.lambda_normal
    )
    m.optimize_exposure = True
    r = m.step(1)
    assert np.isclose(r.loss, total, rtol=1e-5) and np.isclose(r.psnr, psnr.mean(), rtol=1e-5)
    # one Adam step moves each exposure parameter by lr against its gradient's sign
    np.testing.assert_allclose(m.buf.exposure.numpy()[1], exposure - 1e-3 * np.sign(grad_exposure), atol=1e-6)
    assert not m.buf.exposure.numpy()[[0, 2, 3]].any()


def test_anchored_gaussians_move_exactly_with_their_keyframe(fitted):
    """Eq. 12-13 on the parameters and in the render: the Gaussians anchored to keyframe 2
    are visible from its cameras, follow a rigid correction so that the moved cameras see
    the same image, and a scale change renders as Gaussians moved by hand."""
    params = fitted.map.to_numpy()
    a = params["anchors"] == 2
    assert a.any() and (~a).any()
    delta = se3_exp([0.3, -0.1, 0.2, 0.1, -0.2, 0.05])
    R, t = delta[:3, :3], delta[:3, 3]
    gm = GaussianMap(wp.get_device())
    gm.set_numpy(params)
    gm.move_anchored(2, delta, scale=1.5)
    after = gm.to_numpy()
    np.testing.assert_allclose(after["means"][a], params["means"][a] @ R.T + t, atol=1e-5)
    np.testing.assert_array_equal(after["means"][~a], params["means"][~a])
    np.testing.assert_allclose(after["log_scales"][a], params["log_scales"][a] + np.log(1.5), atol=1e-6)
    np.testing.assert_allclose(quat_to_matrix(after["quats"][a]), R @ quat_to_matrix(params["quats"][a]), atol=1e-5)

    only = {k: v[a] for k, v in params.items()}
    T_w_c = fitted.buf.rig.camera_poses(fitted.buf.get_poses()[2])  # the keyframe's 3 cameras

    def draw(p, T):
        g = GaussianMap(wp.get_device())
        g.set_numpy(p)
        out = render(g.gaussians, Views.create(fitted.cams, T))
        return out.color.numpy(), out.alpha.numpy()

    def moved(p, log_scale_change):
        """Eq. 12-13 applied by hand (float64)."""
        q = dict(p, means=p["means"] @ R.T + t, log_scales=p["log_scales"] + log_scale_change)
        q["quats"] = matrix_to_quat(R @ quat_to_matrix(p["quats"])).astype(np.float32)
        return q

    def same_render(a, b):
        """Equal to float32 rounding, except on the few pixels (at most 1 in 10,000) where
        rounding flips a splat across a cutoff (alpha 1/255, 3 sigma): such a flip changes
        the pixel by at most one splat's alpha there, opacity * exp(-4.5) <= 0.012."""
        off = np.abs(a - b).reshape(a.shape[0], a.shape[1], a.shape[2], -1).max(-1) > 2e-4
        assert off.mean() < 1e-4, off.sum()
        np.testing.assert_allclose(a, b, atol=0.012)

    def move(p, scale):
        g = GaussianMap(wp.get_device())
        g.set_numpy(p)
        g.move_anchored(2, delta, scale=scale)
        return g.to_numpy()

    color0, alpha0 = draw(only, T_w_c)
    covered = (alpha0 > 0.5).mean(axis=(1, 2))
    assert covered.max() > 0.02, covered  # the anchored Gaussians are in view (not a vacuous check)
    # Rigid correction: the moved cameras see exactly what the old ones saw.
    color1, alpha1 = draw(move(only, 1.0), delta @ T_w_c)
    same_render(color1, color0)
    same_render(alpha1, alpha0)
    # With a scale change (eq. 13): as the same Gaussians moved by hand, and visibly not as the
    # rigid move alone (so the comparison sees the scale).
    color2, alpha2 = draw(move(only, 1.5), delta @ T_w_c)
    hand_color, hand_alpha = draw(moved(only, np.log(1.5)), delta @ T_w_c)
    same_render(color2, hand_color)
    same_render(alpha2, hand_alpha)
    assert (alpha2 - alpha1).mean() > 0.01 and (alpha2 > 0.5).mean() > (alpha1 > 0.5).mean()


def test_refinement_densifies_in_its_first_half_only(fitted, mapping_seq):
    """A densify step in the second half of the refinement would hand unoptimized clones and
    splits to the outputs: at 95 of a 100-iteration period, an 8-iteration refinement does
    not densify at 100 (its 5th step), a 10-iteration one does (its 5th step is in its first half)."""
    counts = {}
    for n in (8, 10):
        m = make_mapper(mapping_seq, MappingConfig(lr_means=0, lr_log_scales=0, lr_quats=0, lr_opacity=0, lr_colors=0), fitted)
        m.iteration = 95
        calls = []
        m.densify_and_prune = lambda: calls.append(m.iteration)
        joint_refinement(m, n, poses=False, exposure=False)
        counts[n] = calls
        assert m.iteration == 95 + n and m.cfg.densify_every == 100  # the setting is restored
    assert counts == {8: [], 10: [100]}, counts


def test_forgotten_loss_targets_are_made_again_the_same(fitted, mapping_seq):
    """Global BA drops the mapper's cached loss targets (its peak memory): the cache empties,
    and the next steps remake them, so the map they fit is bit for bit the map of steps that
    kept them."""
    maps = []
    for forget in (False, True):
        m = make_mapper(mapping_seq, params=fitted)
        m.optimize(2, densify=False)
        assert len(m.loss._cache) > 0
        if forget:
            m.forget_loss_targets()
            assert len(m.loss._cache) == 0
        m.optimize(4, densify=False)
        maps.append(m.map.to_numpy())
    for name in maps[0]:
        assert np.array_equal(maps[0][name], maps[1][name]), name


def test_exposure_refinement_recovers_gain_and_bias(fitted, mapping_seq):
    cfg = MappingConfig(lr_means=0, lr_log_scales=0, lr_quats=0, lr_opacity=0, lr_colors=0, lr_exposure=0.015, densify_every=0, lambda_ssim=0.0)
    m = make_mapper(mapping_seq, cfg, fitted)
    rng = np.random.default_rng(0)
    truth = np.stack([rng.uniform(0.8, 1.2, (4, 3)), rng.uniform(-0.05, 0.05, (4, 3))], -1)
    for k in range(4):
        m.buf.images[k] = [np.clip(truth[k, c, 0] * img + truth[k, c, 1], 0, 1) for c, img in enumerate(m.buf.keyframe_images(k))]
    joint_refinement(m, 160, poses=False, exposure=True)
    est = exposure_gains(m)
    assert np.abs(est[..., 0] - truth[..., 0]).max() < 0.03
    assert np.abs(est[..., 1] - truth[..., 1]).max() < 0.02


def test_pose_refinement_through_the_renderer_reduces_error(fitted, mapping_seq):
    cfg = MappingConfig(lr_means=0, lr_log_scales=0, lr_quats=0, lr_opacity=0, lr_colors=0, lr_pose=1e-3, densify_every=0)
    m = make_mapper(mapping_seq, cfg, fitted)
    true = m.buf.get_poses()
    bad = true.copy()
    bad[2] = true[2] @ se3_exp([0.02, -0.015, 0.01, 0.01, -0.012, 0.008])
    m.buf.set_poses(bad)

    def err():
        D = np.linalg.inv(true[2]) @ m.buf.get_poses()[2]
        return np.linalg.norm(D[:3, 3]), np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))

    t0, r0 = err()
    m.optimize_poses = True
    for _ in range(60):
        m.step(2)
    t1, r1 = err()
    assert t1 < 0.5 * t0 and r1 < 0.5 * r0, (t0, r0, t1, r1)
    np.testing.assert_array_equal(m.buf.get_poses()[0], true[0])  # the gauge keyframe is fixed


def test_densify_and_prune_counts(fitted, mapping_seq):
    m = make_mapper(mapping_seq, MappingConfig(densify_every=0, split_scale=0.05, prune_floaters=False), fitted)  # the view rules: tests/mapping/test_density.py
    m.step(0)  # creates optimizer state
    d = m.map.to_numpy()
    n = len(d["means"])
    d["opacity_logits"][:10] = -8.0  # near-transparent
    d["log_scales"][10:15] = np.log(3.0)  # oversized
    d["log_scales"][15:20] = np.log(0.2)  # large and hot: split
    d["log_scales"][20:30] = np.log(0.01)  # small and hot: clone
    d["opacity_logits"][15:30] = 2.0  # opaque enough not to be pruned instead
    m.map.set_numpy(d)
    accum, count = np.zeros(n), np.ones(n)
    accum[15:30] = 1.0
    m.map.set_statistics(accum, count)
    # the fitted map may hold a few Gaussians that are prunable on their own
    rest_opacity, rest_scale = 1 / (1 + np.exp(-d["opacity_logits"][30:])), np.exp(d["log_scales"][30:]).max(1)
    natural = int(((rest_opacity < m.cfg.prune_opacity) | (rest_scale > m.cfg.prune_scale)).sum())
    assert natural < 10
    rep = m.densify_and_prune()
    assert (rep.pruned, rep.split, rep.cloned) == (15 + natural, 5, 10)
    assert len(m.map) == n - 15 - natural - 5 + 10 + 2 * 5
    assert m.adam.state["means"][0].shape[0] == 3 * len(m.map)
    after = m.map.to_numpy()
    assert np.all(1 / (1 + np.exp(-after["opacity_logits"])) >= 0.01)
    assert np.isclose(np.exp(after["log_scales"]).max(1), 0.2 / 1.6).sum() == 10  # split children


def test_follow_depth_moves_each_gaussian_along_its_camera_ray(mapping_seq):
    """Eq. 13 per pixel: a keyframe's depth change (new / old on the reduced grid, a
    different field per camera) moves each of its Gaussians along the ray of the camera that
    sees it nearest its image centre by the ratio at its pixel, and scales its size alike;
    Gaussians of other keyframes and ones no camera sees stay put."""
    import warp as wp

    from mcgs_warp.ba.edges import unproject_pixels
    from mcgs_warp.buffer import KeyframeBuffer
    from mcgs_warp.kernels import reference

    rig = mapping_seq.rig
    buf = KeyframeBuffer(rig, stride=8, capacity=2)
    rng = np.random.default_rng(0)
    T_w_b = mapping_seq.groundtruth.poses[3]
    h, w = buf.h, buf.w
    v, u = np.mgrid[0:h, 0:w]
    ratio = np.stack([1.0 + 0.3 * u / (w - 1), np.full((h, w), 0.8), 1.1 - 0.2 * v / (h - 1)]).astype(np.float32)
    pts = []
    for c, spec in enumerate(buf.reduced):  # points anywhere in each camera's view, 2-6 m away
        uv = rng.uniform(0, 1, (150, 2)) * (spec.width - 1, spec.height - 1)
        T = T_w_b @ spec.T_b_c
        X_c = unproject_pixels(spec.warp_camera(), uv) * rng.uniform(2.0, 6.0, (150, 1))
        pts.append(X_c @ T[:3, :3].T + T[:3, 3])
    X = np.concatenate(pts)
    # NumPy reference: the camera that sees each point nearest its image centre, bilinear ratio there
    best, expect, ratios, seen = np.full(len(X), np.inf), X.copy(), np.ones(len(X)), np.zeros(len(X), int)
    for c, spec in enumerate(buf.reduced):
        T = T_w_b @ spec.T_b_c
        Xc = (X - T[:3, 3]) @ T[:3, :3]
        cam = spec.warp_camera()
        with np.errstate(all="ignore"):
            ok = reference.in_domain(cam, Xc)
            p = reference.project(cam, np.where(ok[:, None], Xc, [0.0, 0.0, 1.0]))
        ok &= (p[:, 0] >= 0) & (p[:, 1] >= 0) & (p[:, 0] <= spec.width - 1) & (p[:, 1] <= spec.height - 1)
        seen += ok
        r2 = ((p[:, 0] - (spec.width - 1) / 2) / spec.width) ** 2 + ((p[:, 1] - (spec.height - 1) / 2) / spec.height) ** 2
        take = ok & (r2 < best)
        x0 = np.clip(np.floor(p[take, 0]).astype(int), 0, spec.width - 2)
        y0 = np.clip(np.floor(p[take, 1]).astype(int), 0, spec.height - 2)
        fx, fy = p[take, 0] - x0, p[take, 1] - y0
        R = ratio[c]
        r = R[y0, x0] * (1 - fx) * (1 - fy) + R[y0, x0 + 1] * fx * (1 - fy) + R[y0 + 1, x0] * (1 - fx) * fy + R[y0 + 1, x0 + 1] * fx * fy
        best[take], ratios[take] = r2[take], r
        expect[take] = T[:3, 3] + r[:, None] * (X[take] - T[:3, 3])
    assert (seen >= 2).sum() >= 10, (seen >= 2).sum()  # some points lie where two views overlap
    behind = T_w_b[:3, 3] - 3.0 * T_w_b[:3, 2]  # straight below the rig: no camera sees it
    gm = GaussianMap(wp.get_device())
    gm.append(X, np.full((len(X), 3), 0.5), np.full((len(X), 3), -3.0), anchor=1)
    gm.append(X[:5] + 1.0, np.full((5, 3), 0.5), np.full((5, 3), -2.0), anchor=0)
    gm.append(behind[None], np.full((1, 3), 0.5), np.full((1, 3), -2.0), anchor=1)
    gm.follow_depth(1, T_w_b, rig, buf.cameras, ratio)
    wp.synchronize()
    d = gm.to_numpy()
    n = len(X)
    np.testing.assert_allclose(d["means"][:n], expect, atol=2e-4)
    np.testing.assert_allclose(d["log_scales"][:n, 0], -3.0 + np.log(ratios), atol=1e-4)
    np.testing.assert_allclose(d["means"][n : n + 5], X[:5] + 1.0, atol=1e-6)
    np.testing.assert_allclose(d["means"][-1], behind, atol=1e-6)



def test_background_learns_a_sky_that_no_gaussian_covers(mapping_seq):
    """The top quarter of every image is replaced by a sky at infinity (colour by world
    direction, no depth): with the background the mapper renders it (and a direction no
    keyframe saw in between is interpolated); without it that region stays black (nothing is
    seeded where no depth is: mapping.insert_fill off)."""
    def sky(d):
        return np.clip(0.55 + 0.25 * d[..., 1:2] + 0.15 * d[..., 0:1] * d[..., 2:3] + np.array([0.0, 0.05, 0.1]), 0, 1)

    psnrs = {}
    for background in (True, False):
        from problems import Problem

        from mcgs_warp.mapping.mapper import Mapper

        m = Mapper(Problem(mapping_seq, KEYFRAMES, cross_view=False).buf, config=MappingConfig(background=background, densify_every=0, insert_fill=False))
        poses = m.buf.get_poses()
        masks = []
        for k, f in enumerate(KEYFRAMES):
            images, depths = [], []
            for c, spec in enumerate(m.buf.rig.cameras):
                top = np.zeros((spec.height, spec.width), bool)
                top[: spec.height // 4] = True
                R = (poses[k] @ spec.T_b_c)[:3, :3]
                d = m.full_rays(c) @ R.T
                d /= np.linalg.norm(d, axis=-1, keepdims=True)
                images.append(np.where(top[..., None], sky(d), m.buf.image(k, c)).astype(np.float32))
                depths.append(np.where(top, 0.0, mapping_seq[f].depths[c]).astype(np.float32))
                masks.append(top)
            m.buf.images[k] = images
            m.add_keyframe(k, depths)
        m.optimize(120)
        errs = []
        for k in range(len(KEYFRAMES)):
            colour, _ = m.render(m.views(k))
            col = colour.numpy()
            for c, spec in enumerate(m.buf.rig.cameras):
                top = masks[k * len(m.buf.rig.cameras) + c]
                errs.append(((col[c, : spec.height, : spec.width] - m.buf.image(k, c)) ** 2)[top].mean())
        psnrs[background] = -10 * np.log10(np.mean(errs))
    assert psnrs[True] > 22.0 and psnrs[True] > psnrs[False] + 12.0, psnrs  # 24.4 vs 6.5 dB


def test_new_gaussians_are_sized_by_their_pixel_footprint():
    """Half the spacing of their samples at their range (0.5 stride r / f), at any depth and
    resolution, and however many Gaussians the map already holds nearby."""
    from mcgs_warp.data.resample import resampled_camera
    from mcgs_warp.rig import CameraSpec, Rig

    spec = CameraSpec(name="cam0", model="pinhole", width=64, height=48, intrinsics=(60.0, 60.0, 31.5, 23.5))
    for cam, depth in ((spec, 2.0), (spec, 8.0), (resampled_camera(spec, 128, 96), 8.0)):
        gmap = GaussianMap("cpu")
        image = np.full((cam.height, cam.width, 3), 0.5, np.float32)
        plane = np.full((cam.height, cam.width), depth, np.float32)
        for _ in range(2):  # the second insert lands on the first one's Gaussians
            before = len(gmap)
            gmap.insert_from_depth(Rig([cam]), np.eye(4), [image], [plane], anchor=0, stride=4)
            scales = np.exp(gmap.to_numpy()["log_scales"][before:])
            means = gmap.to_numpy()["means"][before:]
            want = 0.5 * 4 * np.linalg.norm(means, axis=1) / cam.intrinsics[0]
            np.testing.assert_allclose(scales, np.repeat(want[:, None], 3, 1), rtol=1e-5)
        # at the image centre, neighbouring samples on the plane are 4 px x depth / f apart
        assert np.isclose(scales.min(), 0.5 * 4 * depth / cam.intrinsics[0], rtol=0.01)


def test_a_window_of_unregistered_keyframes_maps_nothing(fitted, mapping_seq):
    """Tracking lost over the whole window (no keyframe of it registered) while earlier ones
    are: the window's mapping step does nothing, and over registered ones it steps."""
    m = make_mapper(mapping_seq, params=fitted)
    before = m.map.to_numpy()
    assert m.optimize_window([7, 8, 9], 2) == []
    after = m.map.to_numpy()
    assert all(np.array_equal(before[k], after[k]) for k in before)
    steps = m.optimize_window([2, 3, 7], 2)
    assert len(steps) == 2 and not np.array_equal(m.map.to_numpy()["means"], before["means"])
