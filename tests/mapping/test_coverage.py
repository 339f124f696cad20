"""Covering every camera's view: sky segmentation, seeding where no depth was measured, and
the sky term that keeps Gaussians out of the sky."""

import numpy as np

from conftest import KEYFRAMES
from mcgs_warp.mapping.gaussian_map import GaussianMap, fill_depth
from mcgs_warp.mapping.mapper import MappingConfig
from mcgs_warp.mapping.sky import sky_mask


def street_view(h=96, w=128, seed=0):
    """A grey image: a bright sky (smooth vertical gradient) over the top third, a textured
    tree line and road below; the depth a run would estimate (none in the sky, a few spurious
    matches in it)."""
    rng = np.random.default_rng(seed)
    img = np.empty((h, w, 3), np.float32)
    top = h // 3
    sky = 0.85 + 0.1 * np.linspace(0, 1, top)[:, None] * np.ones((1, w))
    img[:top] = sky[..., None]
    img[top:] = (0.15 + 0.35 * rng.random((h - top, w)))[..., None]
    depth = np.zeros((h, w), np.float32)
    depth[top:] = 20.0
    spurious = rng.random((top, w)) < 0.2  # propagated tree depths inside the sky
    depth[:top][spurious] = 30.0
    return img, depth, top


def test_sky_mask_finds_the_bright_flat_sky_and_nothing_else():
    img, depth, top = street_view()
    mask = sky_mask(img, None)
    assert mask[: top - 3].mean() > 0.98 and mask[top + 3 :].mean() == 0.0
    # a small bright flat patch (a road sign) is not sky
    img2 = img.copy()
    img2[:top] = 0.3 + 0.3 * np.random.default_rng(1).random((top, img.shape[1], 1))  # textured top: no sky at all
    img2[60:66, 20:26] = 1.0
    assert not sky_mask(img2, None).any()


def test_measured_depth_vetoes_a_bright_flat_wall():
    """With exact sensor depth a lit wall that the sensor measures is not sky; the sky, which
    the sensor does not measure, still is."""
    img, depth, top = street_view()
    assert not sky_mask(img, np.full(depth.shape, 3.0, np.float32)).any()
    sensor = depth.copy()
    sensor[:top] = 0.0
    assert sky_mask(img, sensor)[: top - 3].mean() > 0.98


def test_fill_depth_takes_the_neighbourhoods_inverse_depth():
    d = np.zeros((16, 16), np.float32)
    d[:, :8] = 2.0  # a near half and a far half with a hole column between them
    d[:, 9:] = 8.0
    f = fill_depth(d)
    np.testing.assert_array_equal(f[d > 0], d[d > 0])  # measured depth unchanged
    assert (f > 0).all() and ((f[:, 8] >= 2.0) & (f[:, 8] <= 8.0)).all()
    # too few samples for a plane: the harmonic mean of what surrounds the hole
    d2 = np.zeros((8, 8), np.float32)
    d2[0, 0], d2[7, 7] = 2.0, 8.0
    assert np.isclose(fill_depth(d2)[3, 4], 2 / (1 / 2 + 1 / 8), rtol=1e-5)
    assert not fill_depth(np.zeros((4, 4), np.float32)).any()


def test_fill_depth_continues_a_ground_plane_below_where_it_was_measured():
    """A road seen by a pinhole camera (inverse depth linear in the row below the horizon),
    measured only down to row 70: the rows below continue the plane (the near road), where
    a neighbourhood mean would put them at the far depth above."""
    h, w = 96, 128
    v = np.mgrid[0:h, 0:w][0]
    inv = np.clip((v - 40) * 0.01, 0, None)  # horizon at row 40, 2 m at the bottom row
    truth = np.where(inv > 0, 1 / np.maximum(inv, 1e-9), 0).astype(np.float32)
    measured = truth.copy()
    measured[70:] = 0
    f = fill_depth(measured)
    np.testing.assert_allclose(f[70:], truth[70:], rtol=1e-3)
    # a plane beside the measured part too (a wall continued sideways)
    wall = np.broadcast_to(1 / (0.1 + 0.004 * np.arange(w)), (h, w)).astype(np.float32)
    part = wall.copy()
    part[:, 90:] = 0
    np.testing.assert_allclose(fill_depth(part)[:, 90:], wall[:, 90:], rtol=1e-3)


def test_fill_seeds_every_allowed_pixel_without_depth():
    """Without fill only pixels with a depth target seed Gaussians; with it every stride-th
    pixel the mask allows does, at its neighbourhood's depth."""
    from mcgs_warp.rig import CameraSpec, Rig

    cam = CameraSpec(name="c", model="pinhole", width=64, height=48, intrinsics=(60.0, 60.0, 31.5, 23.5))
    image = np.full((48, 64, 3), 0.5, np.float32)
    depth = np.zeros((48, 64), np.float32)
    depth[24:] = 5.0  # the top half measured nothing
    counts = {}
    for fill in (False, True):
        gmap = GaussianMap("cpu")
        counts[fill] = gmap.insert_from_depth(Rig([cam]), np.eye(4), [image], [depth], anchor=0, stride=4, fill=fill, fill_opacity=0.1)
        if fill:
            d = gmap.to_numpy()
            np.testing.assert_allclose(d["means"][:, 2], 5.0, rtol=1e-5)  # the top half takes the bottom's depth
            opacity = 1 / (1 + np.exp(-d["opacity_logits"]))
            guessed = d["means"][:, 1] < 0  # above the image centre: the top half, where nothing was measured
            np.testing.assert_allclose(opacity[guessed], 0.1, rtol=1e-5)  # faint until the colour loss wants them
            np.testing.assert_allclose(opacity[~guessed], 0.9, rtol=1e-5)
    assert counts[False] == 16 * 6 and counts[True] == 16 * 12, counts


def test_sky_term_keeps_gaussians_out_of_the_sky(mapping_seq):
    """Gaussians seeded across the top quarter (as a spurious depth would) where the images
    show a bright flat sky: with the sky term their alpha there falls well below what the
    colour loss alone leaves."""
    from problems import Problem

    from mcgs_warp.mapping.mapper import Mapper

    alphas = {}
    for lam in (0.0, 1.0):
        m = Mapper(Problem(mapping_seq, KEYFRAMES, cross_view=False).buf, config=MappingConfig(sky=True, lambda_sky=lam, densify_every=0, insert_fill=False))
        tops = []
        for k, f in enumerate(KEYFRAMES):
            images, depths, top_k = [], [], []
            for c, spec in enumerate(m.buf.rig.cameras):
                top = np.zeros((spec.height, spec.width), bool)
                top[: spec.height // 4] = True
                images.append(np.where(top[..., None], np.float32(0.9), m.buf.image(k, c)).astype(np.float32))
                depths.append(np.where(top, 6.0, mapping_seq[f].depths[c]).astype(np.float32))
                top_k.append(top)
            m.buf.images[k] = images
            # Gaussians in the sky, as a spurious depth would seed them without the segmentation
            m.map.insert_from_depth(m.buf.rig, m.buf.get_poses()[k], images, depths, anchor=k, mask=top_k)
            m.add_keyframe(k, depths)
            assert all(s[: s.shape[0] // 4 - 2].all() for s in m.sky[k])  # segmented as sky
            tops += top_k
        m.optimize(60)
        a = []
        for k in range(len(KEYFRAMES)):
            _, out = m.render(m.views(k))
            al = out.alpha.numpy()
            for c, spec in enumerate(m.buf.rig.cameras):
                a.append(al[c, : spec.height, : spec.width][tops[k * len(m.buf.rig.cameras) + c]].mean())
        alphas[lam] = float(np.mean(a))
    assert alphas[1.0] < alphas[0.0] - 0.2, alphas  # 0.66 vs 1.00 after 60 steps


def test_sky_masks_survive_a_checkpoint(mapping_seq):
    from problems import Problem

    from mcgs_warp.mapping.mapper import Mapper

    def mapper():
        return Mapper(Problem(mapping_seq, KEYFRAMES[:2], cross_view=False).buf, config=MappingConfig(sky=True, background_cube=4))

    m = mapper()
    for k, f in enumerate(KEYFRAMES[:2]):
        m.buf.images[k] = [np.where(np.arange(s.height)[:, None, None] < s.height // 3, np.float32(0.95), img) for img, s in zip(m.buf.keyframe_images(k), m.buf.rig.cameras)]
        m.add_keyframe(k, mapping_seq[f].depths)
    assert any(mask.any() for mask in m.sky[1])
    m.optimize(2)
    state = m.state_arrays()
    other = mapper()
    other.load_state_arrays(state, {k: m.buf.targets[k] for k in m.buf.targets})
    assert sorted(other.sky) == sorted(m.sky)
    for k in m.sky:
        for a, b in zip(m.sky[k], other.sky[k]):
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(other.background.numpy(), m.background.numpy())


def test_fill_takes_the_keyframes_neighbourhood_not_a_far_layer_the_map_shows(mapping_seq):
    """Where the map is thin (rendered alpha below ``new_alpha``) and nothing measured depth, a
    fill Gaussian takes the plane of its keyframe's measured neighbourhood, not the depth the map
    renders there. On the street the near road's holes showed Gaussians far behind it, and fill
    that took the depth rendered there passed it on (street seed 12, RGB only: depth L1 0.668 m
    with, 0.590 m without)."""
    from problems import Problem

    from mcgs_warp.kernels import render
    from mcgs_warp.mapping.mapper import Mapper

    m = Mapper(Problem(mapping_seq, KEYFRAMES[:1], cross_view=False).buf, config=MappingConfig(densify_every=0))

    def measured_below(scale):
        out = []
        for c, spec in enumerate(m.buf.rig.cameras):
            d = scale * np.asarray(mapping_seq[KEYFRAMES[0]].depths[c], np.float32)
            d[: spec.height // 2] = 0.0  # nothing measured the top half
            out.append(d)
        return out

    m.add_keyframe(0, measured_below(3.0))  # a faint guessed layer over the top half, 3x too far
    n = len(m.map)
    near = measured_below(1.0)
    m.add_keyframe(0, near)
    assert (~m.map.measured[n:]).sum() > 0.3 * n  # the faint top half is seeded again (guessed)
    new = GaussianMap(m.buf.device)
    new.set_numpy({key: v[n:] for key, v in m.map.to_numpy().items()})
    depth = render(new.gaussians, m.views(0)).depth.numpy()
    for c, s in enumerate(m.buf.rig.cameras):
        top = (slice(4, s.height // 2 - 4), slice(4, s.width - 4))
        rendered, plane = depth[c][top], fill_depth(near[c])[top]
        ok = rendered > 0
        assert ok.mean() > 0.9
        # at the neighbourhood's plane (taking the map's depth put them at 3x it)
        assert abs(np.median(rendered[ok] / plane[ok]) - 1) < 0.05, np.median(rendered[ok] / plane[ok])


def test_a_surface_measured_in_front_of_the_map_is_seeded(mapping_seq):
    """Where the map renders behind a measured depth (it covers the view, but with Gaussians
    at a guessed or wrong depth), the measured surface is seeded in front of them."""
    from problems import Problem

    from mcgs_warp.mapping.mapper import Mapper

    m = Mapper(Problem(mapping_seq, KEYFRAMES[:1], cross_view=False).buf, config=MappingConfig(densify_every=0, insert_fill=False))
    truth = [np.asarray(d, np.float32) for d in mapping_seq[KEYFRAMES[0]].depths]
    first = m.add_keyframe(0, [2.0 * d for d in truth])  # the whole view covered, twice too far
    near = []
    for d in truth:
        n = d.copy()
        n[: d.shape[0] // 2] = 0.0  # the top half agrees with nothing: only the bottom half is measured
        near.append(n)
    added = m.add_keyframe(0, near)
    assert 0.3 * first < added < 0.7 * first, (added, first)  # the bottom half, in front
    assert m.add_keyframe(0, near) < 0.05 * first  # and only once


def test_the_confidence_marks_guessed_depth_until_a_view_measures_it(mapping_seq):
    """A keyframe that measured only the bottom half of its views: the fill's Gaussians in the
    top half are marked guessed, the rendered measured share (the confidence PNGs) is low there
    and high below. A depth target that later puts a guessed Gaussian where it is makes it
    measured (at the next densify); one that disagrees (3x as far) does not."""
    from problems import Problem

    from mcgs_warp.kernels import render
    from mcgs_warp.mapping.mapper import Mapper

    def half_measured(m):
        out = []
        for c, spec in enumerate(m.buf.rig.cameras):
            d = np.asarray(mapping_seq[KEYFRAMES[0]].depths[c], np.float32).copy()
            d[: spec.height // 2] = 0.0
            out.append(d)
        return out

    promoted = {}
    for factor in (1.0, 3.0):
        m = Mapper(Problem(mapping_seq, KEYFRAMES[:1], cross_view=False).buf, config=MappingConfig(densify_every=0, densify_grad=1e9))
        m.add_keyframe(0, half_measured(m))
        guessed = ~m.map.measured
        assert 0.3 < guessed.mean() < 0.7, guessed.mean()
        views = m.views(0)
        out = render(m.map.gaussians, views)
        share, _ = m.depth_confidence(out, views)
        for c, spec in enumerate(m.buf.rig.cameras):
            top, bottom = share[c, 8 : spec.height // 2 - 8, 8:-8], share[c, spec.height // 2 + 8 : spec.height - 8, 8 : spec.width - 8]
            assert (top < 0.5).mean() > 0.9 and (bottom >= 0.5).mean() > 0.9, (c, (top < 0.5).mean(), (bottom >= 0.5).mean())
        # a later measurement of the whole view: the depth the map renders there, or 3x that
        rendered = out.depth.numpy()  # (the faint top half has no median depth)
        m.buf.targets[0] = [factor * rendered[c, : s.height, : s.width] for c, s in enumerate(m.buf.rig.cameras)]
        before = {x.tobytes(): g for x, g in zip(m.map.gaussians.means.numpy(), guessed)}
        m.densify_and_prune()  # nothing is cloned or split; what 3x as far leaves in front is pruned as floaters
        was_guessed = np.array([before[x.tobytes()] for x in m.map.gaussians.means.numpy()])
        assert factor != 1.0 or len(m.map) > 0.95 * len(before)
        promoted[factor] = (m.map.measured & was_guessed).sum() / was_guessed.sum()
    assert promoted[1.0] > 0.8 and promoted[3.0] < 0.02, promoted  # (of the guessed Gaussians that survive)


def test_clones_and_split_children_inherit_whether_they_were_measured():
    gmap = GaussianMap("cpu")
    small, large = np.log(np.full((2, 3), 0.01)), np.log(np.full((2, 3), 0.2))
    gmap.append(np.zeros((2, 3)), np.full((2, 3), 0.5), small, anchor=0, measured=True)
    gmap.append(np.ones((2, 3)), np.full((2, 3), 0.5), large, anchor=0, measured=False)
    gmap.set_statistics(np.ones(4), np.ones(4))  # every one hot
    report, index = gmap.densify_and_prune(0.5, 0.05, 0.01, 2.0, 100, np.random.default_rng(0))
    assert (report.cloned, report.split) == (2, 2) and len(gmap) == 8
    scale = np.exp(gmap.to_numpy()["log_scales"]).max(1)
    np.testing.assert_array_equal(gmap.measured, scale < 0.05)  # the small ones and their clones; the split children are not


def test_the_depth_spread_finds_pixels_that_mix_surfaces(mapping_seq):
    """Seeded from the exact depth, the map renders one surface per pixel except at depth
    edges, where splats of both sides blend: the spread of the blended depths around the
    median is small inside surfaces and large on the edges of the true depth (where the
    median depth's error is), so the confidence marks those pixels mixed."""
    import cv2
    from problems import Problem

    from mcgs_warp.kernels import render
    from mcgs_warp.mapping.mapper import Mapper
    from mcgs_warp.system.outputs import MIXED, confidence_levels

    m = Mapper(Problem(mapping_seq, KEYFRAMES[:1], cross_view=False).buf, config=MappingConfig(densify_every=0))
    truth = [np.asarray(d, np.float32) for d in mapping_seq[KEYFRAMES[0]].depths]
    m.add_keyframe(0, truth)
    views = m.views(0)
    out = render(m.map.gaussians, views)
    share, spread = m.depth_confidence(out, views)
    med = out.median_depth.numpy()
    edge_spread, inner_spread, edge_err, inner_err = [], [], [], []
    for c, spec in enumerate(m.buf.rig.cameras):
        d = truth[c]
        logd = np.log(np.maximum(d, 1e-3))
        k = np.ones((5, 5), np.uint8)
        edge = (cv2.dilate(logd, k) - cv2.erode(logd, k)) > 0.2
        s, md = spread[c, : spec.height, : spec.width], med[c, : spec.height, : spec.width]
        ok = (md > 0) & (d > 0)
        edge_spread.append(s[ok & edge])
        inner_spread.append(s[ok & ~edge])
        err = np.abs(md - d) / np.maximum(d, 1e-3)
        edge_err.append(err[ok & edge])
        inner_err.append(err[ok & ~edge])
        level = confidence_levels(share[c], spread[c], med[c])[: spec.height, : spec.width]
        assert (level[ok & edge] == MIXED).mean() > 0.5 and (level[ok & ~edge] == MIXED).mean() < 0.05  # measured: 0.70-0.83 and 0.016-0.025
    edge_spread, inner_spread = np.concatenate(edge_spread), np.concatenate(inner_spread)
    assert len(edge_spread) > 100 and np.median(inner_spread) < 0.04 and np.median(edge_spread) > 3 * np.median(inner_spread), (np.median(edge_spread), np.median(inner_spread))
    assert np.mean(np.concatenate(edge_err)) > 3 * np.mean(np.concatenate(inner_err))  # where the error is
