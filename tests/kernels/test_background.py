"""The background at infinity (kernels/background.py): its basis, its colour by world
direction, and its hand-written adjoint against finite differences and wp.Tape."""

import numpy as np
import pytest
import warp as wp

from warp_devices import devices
from mcgs_warp.kernels import Camera
from mcgs_warp.kernels import background as bg
from mcgs_warp.kernels.ba import grid_rays_kernel
from scenes import cameras, random_pose

MODELS = ["pinhole", "fisheye", "equirectangular"]


@wp.kernel
def basis_kernel(dirs: wp.array(dtype=wp.vec3), out: wp.array(dtype=float, ndim=2)):
    i = wp.tid()
    b = bg.sh_basis(dirs[i])
    for k in range(16):
        out[i, k] = b[k]


def basis(dirs):
    out = wp.zeros((len(dirs), bg.N_COEFFS), dtype=float)
    wp.launch(basis_kernel, dim=len(dirs), inputs=[wp.array(dirs.astype(np.float32), dtype=wp.vec3)], outputs=[out])
    return out.numpy().astype(np.float64)


def test_basis_is_orthonormal_on_the_sphere():
    """4 pi / N sum_i Y_a(d_i) Y_b(d_i) -> delta_ab for uniform directions: a wrong constant
    or a repeated harmonic breaks it."""
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Y = basis(d)
    gram = 4 * np.pi * Y.T @ Y / len(d)
    assert np.abs(gram - np.eye(bg.N_COEFFS)).max() < 0.02


def test_degree_one_terms_point_along_the_world_axes():
    """Y_1 = -c y, Y_2 = c z, Y_3 = -c x (the 3DGS sign convention)."""
    c = 0.4886025119029199
    Y = basis(np.eye(3))
    np.testing.assert_allclose(Y[:, 1:4], [[0, 0, -c], [-c, 0, 0], [0, c, 0]], atol=1e-6)


def setup(model, device, rng, cube=0):
    cam = cameras()[model]
    H, W = cam.height, cam.width
    cams = wp.array([cam, cam], dtype=Camera, device=device)
    rays = wp.zeros((2, H, W), dtype=wp.vec3, device=device)
    wp.launch(grid_rays_kernel, dim=(2, H, W), inputs=[cams], outputs=[rays], device=device)
    T_c_w = np.stack([np.linalg.inv(random_pose(rng)) for _ in range(2)]).astype(np.float32)
    viewmats = wp.array(T_c_w, dtype=wp.mat44, device=device)
    color = rng.uniform(0, 1, (2, H, W, 3)).astype(np.float32)
    alpha = rng.uniform(0, 1, (2, H, W)).astype(np.float32)
    coeffs = rng.normal(size=(bg.n_coeffs(cube), 3)).astype(np.float32)
    return cams, rays, viewmats, T_c_w, color, alpha, coeffs


@pytest.mark.parametrize("device", devices())
def test_background_is_seen_through_the_transmittance_in_world_directions(device):
    rng = np.random.default_rng(1)
    cams, rays, viewmats, T_c_w, color, alpha, coeffs = setup("pinhole", device, rng)
    arr = lambda a, t: wp.array(a, dtype=t, device=device)  # noqa: E731
    out = bg.composite(arr(color, wp.vec3), arr(alpha, float), rays, viewmats, cams, arr(coeffs, wp.vec3)).numpy()
    r = rays.numpy().astype(np.float64)
    d = np.einsum("cji,chwj->chwi", T_c_w[:, :3, :3].astype(np.float64), r)  # R_w_c r = R_c_w^T r
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    want = color + (1 - alpha)[..., None] * (basis(d.reshape(-1, 3)) @ coeffs).reshape(color.shape)
    np.testing.assert_allclose(out, want, atol=2e-5)
    # a cube map adds its texels, looked up by the dominant axis and bilinear between texels:
    # a cube whose every texel is the same colour adds that colour everywhere
    R = 5
    cube = np.concatenate([coeffs, np.tile([[0.1, -0.2, 0.3]], (6 * R * R, 1))]).astype(np.float32)
    with_cube = bg.composite(arr(color, wp.vec3), arr(alpha, float), rays, viewmats, cams, arr(cube, wp.vec3)).numpy()
    np.testing.assert_allclose(with_cube, want + (1 - alpha)[..., None] * np.array([0.1, -0.2, 0.3]), atol=2e-5)
    # opaque splats hide it completely
    opaque = bg.composite(arr(color, wp.vec3), arr(np.ones_like(alpha), float), rays, viewmats, cams, arr(coeffs, wp.vec3)).numpy()
    np.testing.assert_allclose(opaque, color, atol=1e-6)


@pytest.mark.parametrize("device", devices())
@pytest.mark.parametrize("model,cube", [(m, 0) for m in MODELS] + [("equirectangular", 3)])
def test_background_gradients_match_finite_differences(model, cube, device):
    """Harmonics alone, and with a 3x3-texel cube map (an all-around camera sees every face
    and every texel)."""
    rng = np.random.default_rng(2)
    cams, rays, viewmats, _, color, alpha, coeffs = setup(model, device, rng, cube)
    r = rays.numpy()
    r[1, 0, 1:4] = np.nan  # pixels without a ray (as beyond a fisheye's domain)
    rays = wp.array(r, dtype=wp.vec3, device=device)
    w = rng.normal(size=color.shape)  # L = sum w . C_out
    arr = lambda a, t: wp.array(np.asarray(a, np.float32), dtype=t, device=device)  # noqa: E731

    def loss(a, k):
        return float((w * bg.composite(arr(color, wp.vec3), arr(a, float), rays, viewmats, cams, arr(k, wp.vec3)).numpy().astype(np.float64)).sum())

    g_alpha, g_coeffs = bg.composite_backward(arr(alpha, float), rays, viewmats, cams, arr(coeffs, wp.vec3), arr(w, wp.vec3))
    g_alpha, g_coeffs = g_alpha.numpy(), g_coeffs.numpy()
    h = 1e-2  # L is linear in both: the differences are exact up to float32 rounding
    fd = np.zeros_like(coeffs, dtype=np.float64)
    checked = list(np.ndindex(coeffs.shape))
    if cube:  # every harmonic, and a sample of texels on each face
        checked = checked[: 3 * bg.N_COEFFS] + [checked[i] for i in rng.choice(np.arange(3 * bg.N_COEFFS, len(checked)), 36, replace=False)]
    for idx in checked:
        up, dn = coeffs.copy(), coeffs.copy()
        up[idx] += h
        dn[idx] -= h
        fd[idx] = (loss(alpha, up) - loss(alpha, dn)) / (2 * h)
    rows = tuple(np.array(checked).T)
    assert np.abs(g_coeffs[rows] - fd[rows]).max() < 2e-3 * np.abs(fd[rows]).max()
    if cube:
        assert (np.abs(g_coeffs[bg.N_COEFFS :]).sum(1) > 0).all()  # the all-around view reaches every texel
    for c, y, x in [(0, 3, 5), (1, 20, 30), (0, 40, 60), (1, 0, 0)]:
        up, dn = alpha.copy(), alpha.copy()
        up[c, y, x] += h
        dn[c, y, x] -= h
        assert abs(g_alpha[c, y, x] - (loss(up, coeffs) - loss(dn, coeffs)) / (2 * h)) < 2e-3 * (1 + abs(g_alpha[c, y, x]))
    # pixels without a ray get no background and no gradient
    assert np.all(g_alpha[1, 0, 1:4] == 0) and np.all(g_alpha[1, 0, 4:8] != 0)
    out = bg.composite(arr(color, wp.vec3), arr(alpha, float), rays, viewmats, cams, arr(coeffs, wp.vec3)).numpy()
    np.testing.assert_array_equal(out[1, 0, 1:4], color[1, 0, 1:4])


@pytest.mark.parametrize("device", devices())
@pytest.mark.parametrize("cube", [0, 4])
def test_background_adjoint_matches_tape(cube, device):
    rng = np.random.default_rng(3)
    cams, rays, viewmats, _, color, alpha, coeffs = setup("pinhole", device, rng, cube)
    C = wp.array(color, dtype=wp.vec3, device=device, requires_grad=True)
    A = wp.array(alpha, dtype=float, device=device, requires_grad=True)
    K = wp.array(coeffs, dtype=wp.vec3, device=device, requires_grad=True)
    out = wp.zeros(color.shape[:3], dtype=wp.vec3, device=device, requires_grad=True)
    B = wp.zeros(color.shape[:3], dtype=wp.vec3, device=device, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(bg.composite_kernel, dim=color.shape[:3], inputs=[C, A, rays, viewmats, cams, K, cube, 0], outputs=[out, B], device=device)
    g = rng.normal(size=color.shape).astype(np.float32)
    tape.backward(grads={out: wp.array(g, dtype=wp.vec3, device=device)})
    g_alpha, g_coeffs = bg.composite_backward(A, rays, viewmats, cams, K, wp.array(g, dtype=wp.vec3, device=device), background=B)
    np.testing.assert_allclose(C.grad.numpy(), g, atol=1e-6)  # the splats' colour passes through
    np.testing.assert_allclose(g_alpha.numpy(), A.grad.numpy(), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(g_coeffs.numpy(), K.grad.numpy(), rtol=1e-3, atol=1e-3)
