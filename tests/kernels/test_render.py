"""The Warp splatting pipeline against the NumPy brute-force reference, tiling, batching."""

import numpy as np
import pytest

from warp_devices import devices
from mcgs_warp.kernels import Gaussians, Views, bin_tiles, make_camera, project, reference, render
from scenes import cameras, random_pose, random_scene

MODELS = ["pinhole", "fisheye", "equirectangular"]


@pytest.mark.parametrize("device", devices())
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("seed", [0, 1])
def test_render_matches_reference(model, seed, device):
    rng = np.random.default_rng(seed)
    cam = cameras()[model]
    T = random_pose(rng)
    scene = random_scene(rng, 150, model, T)
    out = render(Gaussians.from_numpy(*scene, device=device), Views.create([cam], T[None], device=device))
    C, D, A, M = reference.render(*scene, cam, T, median=True)
    assert A.mean() > 0.1, "scene should cover a good part of the image"
    np.testing.assert_allclose(out.color.numpy()[0], C, atol=1e-5)
    np.testing.assert_allclose(out.alpha.numpy()[0], A, atol=1e-5)
    np.testing.assert_allclose(out.depth.numpy()[0], D, rtol=1e-5, atol=1e-5)
    # median depth: the splat where T crosses 0.5; where T lands within rounding of 0.5 the two may pick neighbours
    near_half = np.abs(A - 0.5) < 1e-4
    assert (M > 0).mean() > 0.05 and ((M > 0) == (A > 0.5))[~near_half].all()
    np.testing.assert_allclose(out.median_depth.numpy()[0][~near_half], M[~near_half], rtol=1e-5, atol=1e-5)


def test_median_depth_is_the_surface_not_a_mix():
    """A faint splat (alpha 0.6 at its centre) at 3 m in front of an opaque wall at 25 m: the
    alpha-normalized depth mixes them (about 12 m, a depth where nothing is); the median depth is the
    faint splat's where its alpha passes 0.5 and the wall's where it leaves T above 0.5; nothing
    covered less than half renders median depth 0."""
    cam = cameras()["pinhole"]
    wall = np.stack(np.meshgrid(np.linspace(-12, 12, 25), np.linspace(-9, 9, 19)), -1).reshape(-1, 2)
    n = len(wall)
    means = np.concatenate([np.c_[wall, np.full(n, 25.0)], [[0.0, 0.0, 3.0]], [[40.0, 0.0, 25.0]]])
    log_scales = np.log(np.concatenate([np.full((n, 3), 0.8), [[0.3, 0.3, 0.3]], [[0.5, 0.5, 0.5]]]))
    opacity = np.concatenate([np.full(n, 8.0), [0.4], [-3.0]])  # opaque wall, the faint splat (sigmoid 0.6), a faint lone one
    colours = np.full((n + 2, 3), 0.5)
    scene = (means, np.tile([0.0, 0.0, 0.0, 1.0], (n + 2, 1)), log_scales, opacity, colours)
    out = render(Gaussians.from_numpy(*scene, device="cpu"), Views.create([cam], np.eye(4)[None], device="cpu"))
    median, mean, alpha = out.median_depth.numpy()[0], out.depth.numpy()[0], out.alpha.numpy()[0]
    cy, cx = int(round(cam.cy)), int(round(cam.cx))
    assert 10.0 < mean[cy, cx] < 18.0, mean[cy, cx]  # the mix
    assert abs(median[cy, cx] - 3.0) < 0.05, median[cy, cx]
    ring = (mean > 14.5) & (mean < 24.5) & (alpha > 0.9)  # the faint splat in front of the wall with alpha below 0.5 (mean = 25 - 22 alpha)
    assert ring.any() and np.allclose(median[ring], 25.0, atol=0.5), median[ring][:5]
    assert (median[alpha < 0.5] == 0).all()



def test_opaque_scene_stops_at_min_transmittance():
    """A wall of opaque splats: blending must stop before T drops below 1e-4."""
    rng = np.random.default_rng(5)
    cam = cameras()["pinhole"]
    T = np.eye(4)
    n = 400
    means = np.stack([rng.uniform(-1, 1, n), rng.uniform(-0.8, 0.8, n), rng.uniform(2, 2.5, n)], 1)
    scene = (means, rng.normal(size=(n, 4)), np.log(np.full((n, 3), 0.3)), np.full(n, 6.0), rng.uniform(0, 1, (n, 3)))
    out = render(Gaussians.from_numpy(*scene), Views.create([cam], T[None]))
    C, D, A = reference.render(*scene, cam, T)
    trans = out.transmittance.numpy()[0]
    assert trans.min() >= 1e-4 and np.median(trans) < 1e-2
    np.testing.assert_allclose(out.color.numpy()[0], C, atol=1e-5)
    np.testing.assert_allclose(out.alpha.numpy()[0], A, atol=1e-5)


def test_batched_rig_equals_single_views():
    """One call over a rig of three different cameras (and sizes) equals three calls."""
    rng = np.random.default_rng(7)
    cams = cameras()
    cams["fisheye"] = make_camera("fisheye", 40, 30, (20.0, 20.0, 19.5, 14.5), (0.02, 0.0, 0.0, 0.0))
    T_w_b = random_pose(rng)
    yaw = {"pinhole": 0.0, "fisheye": np.pi / 2, "equirectangular": -np.pi / 2}
    poses, scenes = [], []
    for name in cams:
        T_b_c = np.eye(4)
        c, s = np.cos(yaw[name]), np.sin(yaw[name])
        T_b_c[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        T_b_c[:3, 3] = rng.normal(size=3) * 0.1
        poses.append(T_w_b @ T_b_c)
        scenes.append(random_scene(rng, 60, name, poses[-1]))
    scene = [np.concatenate(parts) for parts in zip(*scenes)]
    g = Gaussians.from_numpy(*scene)
    batched = render(g, Views.create(list(cams.values()), np.stack(poses)))
    for k, cam in enumerate(cams.values()):
        single = render(g, Views.create([cam], poses[k][None]))
        h, w = cam.height, cam.width
        np.testing.assert_array_equal(batched.color.numpy()[k, :h, :w], single.color.numpy()[0])
        np.testing.assert_array_equal(batched.depth.numpy()[k, :h, :w], single.depth.numpy()[0])
        assert single.alpha.numpy()[0].mean() > 0.05
        assert not batched.alpha.numpy()[k, h:, :].any() and not batched.alpha.numpy()[k, :, w:].any()


def test_tile_bins_are_sorted_and_exact():
    """Keys sorted by (tile, depth); every listed tile really is reached by its splat's
    ellipse, and every pixel a splat contributes to lies in a listed tile."""
    rng = np.random.default_rng(8)
    cam = cameras()["pinhole"]
    T = random_pose(rng)
    scene = random_scene(rng, 80, "pinhole", T)
    g, v = Gaussians.from_numpy(*scene), Views.create([cam], T[None])
    proj = project(g, v)
    bins = bin_tiles(proj, v)
    keys = bins.keys.numpy()[: bins.count]
    vals = bins.values.numpy()[: bins.count]
    assert np.all(np.diff(keys) >= 0)
    tiles = keys >> 32
    depth = proj.depth.numpy()
    np.testing.assert_array_equal((keys & 0xFFFFFFFF).astype(np.uint32).view(np.float32), depth[vals])
    start, end = bins.tile_start.numpy(), bins.tile_end.numpy()
    for t in np.unique(tiles):
        assert np.all(tiles[start[t] : end[t]] == t) and end[t] - start[t] == np.sum(tiles == t)
    # brute force: pixels with alpha >= 1/255 and m <= 9 per splat
    mu, q, o = proj.mean2d.numpy(), proj.conic.numpy(), proj.opacity.numpy()
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    listed = set(zip(vals.tolist(), tiles.tolist()))
    reached_tiles = 0
    for i in np.nonzero(proj.visible.numpy())[0]:
        dx, dy = xs - mu[i, 0], ys - mu[i, 1]
        m = q[i, 0] * dx * dx + 2 * q[i, 1] * dx * dy + q[i, 2] * dy * dy
        hit = (m <= 9) & (o[i] * np.exp(-0.5 * m) >= 1 / 255)
        needed = set(((ys[hit] // 16) * v.tiles_x + xs[hit] // 16).tolist())
        assert needed <= {t for (j, t) in listed if j == i}
        reached_tiles += len(needed)
    assert reached_tiles > 0.8 * bins.count  # the exact test keeps few useless tiles


def test_nothing_visible_renders_empty():
    cam = cameras()["pinhole"]
    n = 5
    means = np.tile([0.0, 0.0, -3.0], (n, 1))  # behind the camera
    scene = (means, np.tile([0, 0, 0, 1.0], (n, 1)), np.zeros((n, 3)), np.zeros(n), np.ones((n, 3)))
    out = render(Gaussians.from_numpy(*scene), Views.create([cam], np.eye(4)[None]))
    assert out.bins.count == 0
    assert not out.alpha.numpy().any() and not out.color.numpy().any()


def test_cpu_worker_count_does_not_change_results(monkeypatch):
    """Row bands over 1, 2 or 3 CPU threads (``MCGS_WARP_CPU_THREADS``) give bitwise the
    same images and the same gradients up to float32 summation order (each worker sums
    into buffers of its own, added in worker order)."""
    from mcgs_warp.kernels import render_backward

    rng = np.random.default_rng(9)
    cam = cameras()["fisheye"]
    T = random_pose(rng)
    g = Gaussians.from_numpy(*random_scene(rng, 120, "fisheye", T))
    v = Views.create([cam, cameras()["pinhole"]], np.stack([T, T]))
    gC = rng.normal(size=(2, v.height, v.width, 3))
    images = ("color", "depth", "alpha", "transmittance", "n_contrib")
    gradients = ("means", "quats", "log_scales", "opacity_logits", "colors", "pose", "mean2d")
    results = []
    for workers in ("1", "2", "3"):
        monkeypatch.setenv("MCGS_WARP_CPU_THREADS", workers)
        out = render(g, v)
        grads = render_backward(g, v, out, grad_color=gC, grad_depth=gC[..., 0], grad_alpha=gC[..., 1])
        results.append({k: getattr(out, k).numpy().copy() for k in images} | {k: getattr(grads, k).numpy().copy() for k in gradients})
    for other in results[1:]:
        for k in images:
            np.testing.assert_array_equal(other[k], results[0][k], err_msg=k)
        for k in gradients:
            a = results[0][k]
            assert np.abs(a).max() > 0, k
            np.testing.assert_allclose(other[k], a, rtol=0, atol=2e-5 * np.abs(a).max(), err_msg=k)


def test_splats_far_outside_the_image_are_culled_with_finite_gradients():
    """A Gaussian 10 cm in front of the camera plane but 1.5 m to the side projects
    millions of pixels away; it must be culled, not overflow the backward pass."""
    from mcgs_warp.kernels import render_backward

    cam = cameras()["pinhole"]
    means = np.array([[-1.5, 0.2, 0.1], [0.0, 0.0, 2.0]])
    scene = (means, np.tile([0, 0, 0, 1.0], (2, 1)), np.log(np.full((2, 3), 0.05)), np.full(2, 2.0), np.ones((2, 3)))
    g, v = Gaussians.from_numpy(*scene), Views.create([cam], np.eye(4)[None])
    out = render(g, v)
    assert out.projection.visible.numpy().tolist() == [0, 1]
    grads = render_backward(g, v, out, grad_color=np.ones((1, cam.height, cam.width, 3)), grad_depth=np.ones((1, cam.height, cam.width)))
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        assert np.isfinite(getattr(grads, name).numpy()).all()
    assert np.abs(grads.means.numpy()[1]).sum() > 0


def test_cpu_tile_kernels_equal_the_per_pixel_kernels():
    """On the CPU blending runs one thread per tile, each splat visiting only its box of
    pixels; CUDA runs one thread per pixel. Both forms on the CPU, on a rig of different
    image sizes (padding) with opaque splats (early stop, alpha clamped at 0.99): the images
    are bitwise equal and the splat gradients equal up to float32 summation order."""
    import warp as wp

    from mcgs_warp.kernels import render_backward
    from mcgs_warp.kernels.blend import blend_backward_kernel, blend_kernel

    rng = np.random.default_rng(11)
    small = make_camera("fisheye", 40, 30, (20.0, 20.0, 19.5, 14.5), (0.02, 0.0, 0.0, 0.0))
    cams = [cameras()["pinhole"], small, cameras()["equirectangular"]]
    T = random_pose(rng)
    parts = [random_scene(rng, 150, m, T, scale=(0.02, 0.4)) for m in ("pinhole", "fisheye", "equirectangular")]
    scene = [np.concatenate(p) for p in zip(*parts)]
    scene[3][::3] = 6.0  # opacity 0.9975: clamped alpha, and pixels that stop early
    g = Gaussians.from_numpy(*scene, device="cpu")
    v = Views.create(cams, np.stack([T, T, T]), device="cpu")
    out = render(g, v)
    shape = (v.n, v.height, v.width)
    assert out.transmittance.numpy().min() < 1e-3  # some pixels stop before the end of their list
    tiles = [v.tiles_x, v.tiles_x * v.tiles_y]
    ref = [wp.empty(shape, dtype=t, device="cpu") for t in (wp.vec3, float, float, float, wp.int32, float)]
    wp.launch(blend_kernel, dim=shape, inputs=[out.records, out.record_colors, out.bins.tile_start, out.bins.tile_end, v.cameras, *tiles, 0], outputs=ref, device="cpu")
    for name, r in zip(("color", "depth", "alpha", "transmittance", "n_contrib", "median_depth"), ref):
        np.testing.assert_array_equal(getattr(out, name).numpy(), r.numpy(), err_msg=name)

    gC, gD, gA = rng.normal(size=shape + (3,)), rng.normal(size=shape), rng.normal(size=shape)
    grads = render_backward(g, v, out, grad_color=gC, grad_depth=gD, grad_alpha=gA)
    n, total = g.n, out.projection.mean2d.shape[0]
    per_pixel = [wp.zeros(total, dtype=t, device="cpu") for t in (wp.vec2, wp.vec3, float, float)] + [wp.zeros(n, dtype=wp.vec3, device="cpu")]
    images = [wp.array(a.astype(np.float32), dtype=t, device="cpu") for a, t in ((gC, wp.vec3), (gD, float), (gA, float))]
    forward = [out.color, out.depth, out.alpha, out.transmittance, out.n_contrib]
    wp.launch(blend_backward_kernel, dim=shape, inputs=[out.records, out.record_colors, out.bins.values, out.bins.tile_start, v.cameras, n, *tiles, 0, *forward, *images], outputs=per_pixel, device="cpu")
    from mcgs_warp.kernels.splat import blend_backward

    tiled = blend_backward(out, v, gC, gD, gA)
    for name, r in zip(("mean2d", "conic", "opacity", "depth", "colors"), per_pixel):
        a, b = getattr(tiled, name).numpy(), r.numpy()
        assert np.abs(b).max() > 0, name
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5 * np.abs(b).max(), err_msg=name)
    np.testing.assert_array_equal(grads.mean2d.numpy(), tiled.mean2d.numpy())


def test_cpu_tile_box_keeps_every_pixel_of_long_thin_splats():
    """Needle-like splats (long, thin, slanted: the terms of d^T conic d cancel, so float32
    rounds it by more than the ellipse's own margin) still blend the same pixels in the
    per-tile CPU kernel as in the per-pixel one."""
    import warp as wp
    from scipy.spatial.transform import Rotation

    from mcgs_warp.kernels.blend import blend_kernel

    rng = np.random.default_rng(0)
    cam = make_camera("pinhole", 1000, 1000, (500.0, 500.0, 499.5, 499.5), ())
    n = 300
    means = np.stack([rng.uniform(-0.2, 0.2, n), rng.uniform(-0.2, 0.2, n), np.full(n, 1.0)], 1)
    quats = Rotation.from_rotvec(np.stack([np.zeros(n), np.zeros(n), rng.uniform(0, np.pi, n)], 1)).as_quat()
    log_scales = np.log(np.stack([rng.uniform(0.25, 0.35, n), np.full(n, 1e-4), np.full(n, 1e-4)], 1))
    g = Gaussians.from_numpy(means, quats, log_scales, np.full(n, -2.0), rng.uniform(0, 1, (n, 3)), device="cpu")
    v = Views.create([cam], np.eye(4)[None], device="cpu")
    out = render(g, v)
    shape = (1, v.height, v.width)
    ref = [wp.empty(shape, dtype=t, device="cpu") for t in (wp.vec3, float, float, float, wp.int32, float)]
    wp.launch(blend_kernel, dim=shape, inputs=[out.records, out.record_colors, out.bins.tile_start, out.bins.tile_end, v.cameras, v.tiles_x, v.tiles_x * v.tiles_y, 0], outputs=ref, device="cpu")
    assert (out.alpha.numpy() > 0).mean() > 0.01
    for name, r in zip(("color", "depth", "alpha", "transmittance", "n_contrib", "median_depth"), ref):
        np.testing.assert_array_equal(getattr(out, name).numpy(), r.numpy(), err_msg=name)
