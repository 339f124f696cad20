"""Mapping losses: the device kernels against the NumPy reference (the former host loss),
against eval.metrics.ssim and against finite differences; Adam against NumPy."""

import numpy as np
import pytest
import warp as wp

from loss_reference import color_loss, depth_loss, keyframe_loss, normal_loss
from mcgs_warp.eval.metrics import ssim
from mcgs_warp.kernels.camera import make_camera
from mcgs_warp.mapping.losses import MappingLoss
from mcgs_warp.mapping.optimizer import Adam

SIZES = [(20, 24), (13, 17)]  # (h, w) per camera: the second is padded into the first's size
LAMBDAS = (0.2, 0.05, 0.5)  # ssim, depth, normal (normal raised so that its gradient counts)


class Problem:
    """Two pinhole cameras of different sizes, targets, and renders that differ from the
    targets by at least 0.02 everywhere (so a finite-difference step of 1e-3 never crosses
    an L1 kink); one unknown target depth and one empty rendered pixel."""

    def __init__(self, seed=0, with_depth=(True, True)):
        rng = np.random.default_rng(seed)
        self.cams = [make_camera("pinhole", 24, 20, (20, 20, 11.5, 9.5)), make_camera("pinhole", 17, 13, (15, 15, 8, 6))]
        C, H, W = len(SIZES), 20, 24
        self.exposure = np.array([[0.1, 0.02], [-0.05, -0.03]], np.float32)
        self.color = np.zeros((C, H, W, 3), np.float32)
        self.depth = np.zeros((C, H, W), np.float32)
        self.images, self.depths = [], []
        for c, (h, w) in enumerate(SIZES):
            img = rng.uniform(0.1, 0.9, (h, w, 3)).astype(np.float32)
            v, u = np.mgrid[0:h, 0:w]
            d_t = (2.0 + 0.3 * np.sin(u / 4.0) + 0.2 * np.cos(v / 3.0)).astype(np.float32)
            d_t[2, 3] = 0.0  # no target here
            pred = img + rng.choice([-1, 1], img.shape) * (0.02 + 0.05 * rng.uniform(size=img.shape))
            self.color[c, :h, :w] = (pred - self.exposure[c, 1]) / np.exp(self.exposure[c, 0])
            self.depth[c, :h, :w] = d_t + rng.choice([-1, 1], d_t.shape) * (0.02 + 0.03 * rng.uniform(size=d_t.shape))
            self.depth[c, 5, 6] = 0.0  # nothing rendered here
            self.images.append(img)
            self.depths.append(d_t if with_depth[c] else None)
        self.loss = MappingLoss(self.cams, wp.get_device())
        self.targets = self.loss.make_targets(self.images, self.depths)
        self.rays = [self.loss.rays.numpy()[c, :h, :w].astype(np.float64) for c, (h, w) in enumerate(SIZES)]

    def device(self, color=None, depth=None, exposure=None, lambdas=LAMBDAS):
        """Device loss: (total, grad colour, grad depth, grad exposure, PSNR [C])."""
        color = self.color if color is None else color
        depth = self.depth if depth is None else depth
        exposure = self.exposure if exposure is None else exposure
        r = self.loss(
            wp.array(color.astype(np.float32), dtype=wp.vec3),
            wp.array(depth.astype(np.float32), dtype=float),
            self.targets,
            wp.array(exposure.astype(np.float32), dtype=float),
            *lambdas,
        )
        total, psnr = r.values()
        return total, r.grad_color.numpy().copy(), r.grad_depth.numpy().copy(), r.grad_exposure.numpy().copy(), psnr

    def host(self, lambdas=LAMBDAS):
        return keyframe_loss(self.color, self.depth, SIZES, self.images, self.depths, self.rays, self.exposure.astype(np.float64), *lambdas)


@pytest.fixture(scope="module")
def problem():
    return Problem()


def fd_mismatch(f, x, grad, entries, h):
    """Largest relative mismatch between ``grad`` and central differences of ``f`` at
    ``entries`` of ``x`` (a scale floor of 5 % of the largest |grad| keeps tiny entries
    from dominating)."""
    floor = 0.05 * np.abs(grad).max()
    worst = 0.0
    for idx in entries:
        xp, xm = x.copy(), x.copy()
        xp[idx] += h
        xm[idx] -= h
        fd = (f(xp) - f(xm)) / (2 * h)
        worst = max(worst, abs(grad[idx] - fd) / max(abs(fd), floor))
    return worst


def directional_mismatch(f, x, grad, rng, h, n=3):
    """Relative mismatch of directional derivatives along random directions, masked to
    where ``grad`` is non-zero (the cameras' pixels) and ``x`` is not 0 (an empty rendered
    pixel: moving it off 0 switches quads of the normal term on, a discontinuity)."""
    worst = 0.0
    for _ in range(n):
        v = rng.normal(size=x.shape) * ((grad != 0) & (x != 0))
        fd = (f(x + h * v) - f(x - h * v)) / (2 * h)
        an = float(np.sum(grad * v))
        worst = max(worst, abs(an - fd) / abs(fd))
    return worst


# --- against the NumPy reference ---------------------------------------------------------


@pytest.mark.parametrize("lambdas", [LAMBDAS, (0.0, 0.05, 0.05), (1.0, 0.0, 0.0)])
def test_device_loss_matches_the_host_reference(problem, lambdas):
    total, gC, gD, gE, psnr = problem.device(lambdas=lambdas)
    ref_total, ref_gC, ref_gD, ref_gE, ref_psnr = problem.host(lambdas)
    assert np.isclose(total, ref_total, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(psnr, ref_psnr, rtol=1e-6)
    np.testing.assert_allclose(gC, ref_gC, rtol=1e-4, atol=1e-5 * np.abs(ref_gC).max())
    np.testing.assert_allclose(gD, ref_gD, rtol=1e-4, atol=1e-5 * max(np.abs(ref_gD).max(), 1e-12))
    np.testing.assert_allclose(gE, ref_gE, rtol=1e-4, atol=1e-6)
    for c, (h, w) in enumerate(SIZES):  # nothing leaks into the padding
        assert not gC[c, h:].any() and not gC[c, :, w:].any() and not gD[c, h:].any() and not gD[c, :, w:].any()


def test_camera_without_depth_has_no_depth_or_normal_terms():
    p = Problem(with_depth=(True, False))
    total, gC, gD, gE, _ = p.device()
    ref = p.host()
    assert np.isclose(total, ref[0], rtol=1e-6)
    assert not gD[1].any() and np.abs(gD[0]).max() > 0
    np.testing.assert_allclose(gD, ref[2], rtol=1e-4, atol=1e-5 * np.abs(ref[2]).max())


@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a second Warp device (CUDA)")
def test_arrays_on_another_device_are_an_error_not_a_crash(problem):
    other = "cpu" if problem.loss.device.is_cuda else "cuda:0"
    color = wp.array(problem.color, dtype=wp.vec3, device=other)
    depth = wp.array(problem.depth, dtype=float, device=problem.loss.device)
    exposure = wp.array(problem.exposure, dtype=float, device=problem.loss.device)
    with pytest.raises(ValueError, match="color is on"):
        problem.loss(color, depth, problem.targets, exposure, *LAMBDAS)


def test_ssim_kernel_matches_eval_metrics(problem):
    """With l_ssim = 1 and identity exposure the loss is 1 - SSIM per camera."""
    color = problem.color.copy()
    _, gC, _, _, _ = problem.device(color=color, exposure=np.zeros((2, 2)), lambdas=(1.0, 0.0, 0.0))
    total = problem.device(color=color, exposure=np.zeros((2, 2)), lambdas=(1.0, 0.0, 0.0))[0]
    expected = 0.0
    for c, (h, w) in enumerate(SIZES):
        s, g = ssim(color[c, :h, :w], problem.images[c])
        expected += 1.0 - s
        np.testing.assert_allclose(gC[c, :h, :w], -g, rtol=1e-4, atol=1e-5 * np.abs(g).max())
    assert np.isclose(total, expected, rtol=1e-6, atol=1e-7)


def test_targets_are_cached_per_keyframe_and_remade_when_replaced(problem):
    """Targets stay on the device per keyframe (the same object while its host arrays are the
    same), are remade when they are replaced, and the least recently used keyframe leaves once
    the byte budget is spent (here: two keyframes)."""
    one = MappingLoss(problem.cams, wp.get_device()).keyframe_bytes
    assert MappingLoss(problem.cams, wp.get_device(), cache_bytes=5 * one + one // 2).cache_size == 5
    loss = MappingLoss(problem.cams, wp.get_device(), cache_bytes=2 * one)
    assert loss.cache_size == 2
    a = loss.targets(0, problem.images, problem.depths)
    assert loss.targets(0, problem.images, problem.depths) is a
    new_images = [img.copy() for img in problem.images]
    b = loss.targets(0, new_images, problem.depths)
    assert b is not a
    loss.targets(1, problem.images, problem.depths)
    loss.targets(2, problem.images, problem.depths)
    assert loss.targets(1, problem.images, problem.depths) is not None and 0 not in loss._cache  # LRU drops keyframe 0


# --- against finite differences (float32 kernels) -----------------------------------------


def test_colour_gradient_matches_finite_differences(problem):
    _, gC, _, _, _ = problem.device()

    def f(x):
        return problem.device(color=x)[0]

    entries = [(0, 0, 0, 0), (0, 10, 12, 1), (0, 19, 23, 2), (1, 6, 8, 0), (1, 12, 16, 1), (1, 0, 3, 2)]
    assert fd_mismatch(f, problem.color, gC, entries, 1e-3) < 5e-3
    assert directional_mismatch(f, problem.color, gC, np.random.default_rng(1), 1e-3) < 1e-2


def test_depth_gradient_matches_finite_differences(problem):
    """Depth L1 and the normal term (a pixel's gradient gathers three quads)."""
    _, _, gD, _, _ = problem.device()

    def f(x):
        return problem.device(depth=x)[0]

    entries = [(0, 0, 0), (0, 7, 9), (0, 19, 23), (0, 3, 3), (0, 5, 7), (1, 6, 8), (1, 12, 16), (1, 0, 5)]
    assert fd_mismatch(f, problem.depth, gD, entries, 1e-3) < 5e-3
    assert directional_mismatch(f, problem.depth, gD, np.random.default_rng(2), 1e-3) < 1e-2


def test_exposure_gradient_matches_finite_differences(problem):
    _, _, _, gE, _ = problem.device()

    def f(x):
        return problem.device(exposure=x)[0]

    entries = [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert fd_mismatch(f, problem.exposure.astype(np.float64), gE, entries, 1e-3) < 5e-3


def test_a_broken_gradient_fails_the_checks(problem):
    """The checks above have teeth: the normal gradient shifted by one pixel (a plausible
    gather bug) and the SSIM gradient without its window blur both fail them."""
    _, _, gD, _, _ = problem.device()
    _, _, gD_depth_only, _, _ = problem.device(lambdas=(LAMBDAS[0], LAMBDAS[1], 0.0))
    shifted = gD_depth_only + np.roll(gD - gD_depth_only, 1, axis=2)

    def f(x):
        return problem.device(depth=x)[0]

    entries = [(0, 7, 9), (0, 3, 3), (1, 6, 8), (1, 12, 16)]
    assert fd_mismatch(f, problem.depth, shifted, entries, 1e-3) > 0.1
    assert directional_mismatch(f, problem.depth, shifted, np.random.default_rng(2), 1e-3) > 0.05

    lam = (1.0, 0.0, 0.0)
    _, gC, _, _, _ = problem.device(lambdas=lam)
    unblurred = gC.copy()
    for c, (h, w) in enumerate(SIZES):
        unblurred[c, :h, :w] = gC[c, :h, :w].mean() + (gC[c, :h, :w] - gC[c, :h, :w].mean()) * 0.5

    def g(x):
        return problem.device(color=x, lambdas=lam)[0]

    assert directional_mismatch(g, problem.color, unblurred, np.random.default_rng(3), 1e-3) > 0.05


# --- the NumPy reference itself (float64) -------------------------------------------------


def test_reference_ssim_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    y = rng.uniform(0, 1, (20, 24, 3))
    x = np.clip(y + rng.normal(scale=0.1, size=y.shape), 0, 1)
    s, g = ssim(x, y)
    assert 0 < s < 1
    for idx in [(0, 0, 0), (5, 7, 1), (19, 23, 2), (10, 12, 0)]:
        h = 1e-3
        xp, xm = x.copy(), x.copy()
        xp[idx] += h
        xm[idx] -= h
        fd = (ssim(xp, y, False)[0] - ssim(xm, y, False)[0]) / (2 * h)
        assert abs(g[idx] - fd) < 1e-2 * abs(fd) + 1e-6, (idx, g[idx], fd)  # float32 SSIM
    assert np.isclose(ssim(y, y, False)[0], 1.0, atol=1e-6)


def test_reference_color_and_depth_losses():
    rng = np.random.default_rng(1)
    y = rng.uniform(0, 1, (8, 9, 3))
    x = y + 0.1
    v, g = color_loss(x, y, lambda_ssim=0.0)
    assert np.isclose(v, 0.1) and np.allclose(g, 1.0 / y.size)
    d_t = np.array([[1.0, 0.0], [2.0, 3.0]])
    v, g = depth_loss(np.array([[1.5, 9.0], [1.0, 3.0]]), d_t)
    assert np.isclose(v, (0.5 + 1.0 + 0.0) / 3) and g[0, 1] == 0 and np.isclose(g[1, 0], -1 / 3)


def test_reference_normal_loss_gradient_matches_finite_differences():
    rng = np.random.default_rng(4)
    H, W = 9, 11
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - 5.0) / 8.0, (v - 4.0) / 8.0, np.ones((H, W))], -1)
    target = 3.0 + 0.2 * u / W + 0.1 * np.sin(v)  # a curved surface
    depth = target + rng.normal(scale=0.05, size=(H, W))
    depth[0, 0] = 0.0  # unknown pixels do not count
    value, grad = normal_loss(depth, target, rays)
    assert 0 < value < 1
    assert normal_loss(target, target, rays)[0] < 1e-12
    for idx in [(3, 4), (0, 5), (8, 10), (4, 0)]:
        e = np.zeros((H, W))
        e[idx] = 1e-6
        fd = (normal_loss(depth + e, target, rays)[0] - normal_loss(depth - e, target, rays)[0]) / 2e-6
        assert abs(grad[idx] - fd) < 1e-5 + 1e-4 * abs(fd), (idx, grad[idx], fd)


# --- optimizer and regularizer --------------------------------------------------------------


def test_adam_matches_numpy():
    rng = np.random.default_rng(2)
    p0 = rng.normal(size=(5, 3)).astype(np.float32)
    p = wp.array(p0, dtype=wp.vec3)
    opt = Adam({"x": 0.1})
    m = np.zeros_like(p0, dtype=np.float64)
    v = np.zeros_like(m)
    ref = p0.astype(np.float64)
    for t in range(1, 4):
        g = rng.normal(size=p0.shape).astype(np.float32)
        opt.step({"x": p}, {"x": wp.array(g, dtype=wp.vec3)})
        m = 0.9 * m + 0.1 * g
        v = 0.999 * v + 0.001 * g * g
        ref -= 0.1 * (m / (1 - 0.9**t)) / (np.sqrt(v / (1 - 0.999**t)) + 1e-15)
    np.testing.assert_allclose(p.numpy(), ref, rtol=1e-5, atol=1e-6)


def test_adam_groups_on_array_slices_count_their_own_steps():
    """Exposure groups step one keyframe's slice of a [K,C,2] array, each with its own
    bias correction: the first step of any group moves every entry by lr * sign(g)."""
    e = wp.zeros((3, 2, 2), dtype=float)
    opt = Adam({})
    g = wp.array(np.array([[0.5, -2.0], [1e-3, 3.0]], np.float32), dtype=float)
    opt.step_group("exposure1", e[1], g, 0.01)
    opt.step_group("exposure2", e[2], g, 0.01)
    opt.step_group("exposure1", e[1], g, 0.01)
    out = e.numpy()
    assert not out[0].any()
    np.testing.assert_allclose(out[2], -0.01 * np.sign(g.numpy()), rtol=1e-5)
    np.testing.assert_allclose(out[1], -0.02 * np.sign(g.numpy()), rtol=1e-5)
    assert opt.state["exposure1"][2] == 2 and opt.state["exposure2"][2] == 1


def test_isotropy_regularizer_gradient():
    from mcgs_warp.kernels.mapping import isotropy_loss_kernel

    rng = np.random.default_rng(3)
    ls = rng.normal(-2, 0.5, (6, 3)).astype(np.float64)

    def run(x):
        loss = wp.zeros(1, dtype=float)
        grad = wp.zeros(len(x), dtype=wp.vec3)
        wp.launch(isotropy_loss_kernel, dim=len(x), inputs=[wp.array(x.astype(np.float32), dtype=wp.vec3), 0.7], outputs=[loss, grad])
        return float(loss.numpy()[0]), grad.numpy()

    def ref(x):
        s = np.exp(x)
        return 0.7 * np.abs(s - s.mean(1, keepdims=True)).sum()

    value, grad = run(ls)
    assert np.isclose(value, ref(ls), rtol=1e-5)
    for i, k in [(0, 0), (3, 2), (5, 1)]:
        e = np.zeros_like(ls)
        e[i, k] = 1e-4
        fd = (ref(ls + e) - ref(ls - e)) / 2e-4
        assert np.isclose(grad[i, k], fd, rtol=1e-3, atol=1e-6)
