"""Loss gradients against finite differences; Adam against a NumPy reference."""

import numpy as np
import warp as wp

from mcgs_warp.mapping.losses import color_loss, depth_loss, ssim
from mcgs_warp.mapping.optimizer import Adam


def test_ssim_gradient_matches_finite_differences():
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


def test_color_and_depth_losses():
    rng = np.random.default_rng(1)
    y = rng.uniform(0, 1, (8, 9, 3))
    x = y + 0.1
    v, g = color_loss(x, y, lambda_ssim=0.0)
    assert np.isclose(v, 0.1) and np.allclose(g, 1.0 / y.size)
    d_t = np.array([[1.0, 0.0], [2.0, 3.0]])
    v, g = depth_loss(np.array([[1.5, 9.0], [1.0, 3.0]]), d_t)
    assert np.isclose(v, (0.5 + 1.0 + 0.0) / 3) and g[0, 1] == 0 and np.isclose(g[1, 0], -1 / 3)


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


def test_normal_loss_gradient_matches_finite_differences():
    from mcgs_warp.mapping.losses import normal_loss

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
