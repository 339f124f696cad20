"""Hand-written adjoints of the splatting pipeline.

* Against central finite differences (float64) of the NumPy reference renderer,
  for every parameter group and the camera pose, on every camera model.
* Against Warp's own autodiff (wp.Tape) of the projection kernel.
"""

import numpy as np
import pytest
import warp as wp
from scipy.linalg import expm

from warp_devices import devices
from mcgs_warp.kernels import Camera, Gaussians, Views, reference, render, render_backward
from mcgs_warp.kernels.projection import project_gaussians_backward_kernel, project_gaussians_kernel
from mcgs_warp.kernels.se3 import vec6
from scenes import cameras, random_pose, random_scene

MODELS = ["pinhole", "fisheye", "equirectangular"]
GROUPS = ["means", "quats", "log_scales", "opacity_logits", "colors"]


def hat(xi):
    X = np.zeros((4, 4))
    X[:3, :3] = [[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]]
    X[:3, 3] = xi[:3]
    return X


def assert_grad_close(name, got, want, rtol=3e-3):
    scale = np.abs(want).max()
    assert scale > 0, f"{name}: finite differences are all zero"
    err = np.abs(got - want).max() / scale
    assert err < rtol, f"{name}: max error {err:.2e} of scale {scale:.3e}\n got {got.ravel()[:8]}\nwant {want.ravel()[:8]}"


@pytest.mark.parametrize("device", devices())
@pytest.mark.parametrize("model", MODELS)
def test_render_gradients_match_finite_differences(model, device):
    rng = np.random.default_rng(11)
    cam = cameras()[model]
    T = random_pose(rng)
    params = dict(zip(GROUPS, random_scene(rng, 12, model, T, scale=(0.05, 0.3))))
    H, W = cam.height, cam.width
    wC, wD, wA = rng.normal(size=(H, W, 3)), rng.normal(size=(H, W)), rng.normal(size=(H, W))

    def loss(p, T_w_c):
        C, D, A = reference.render(*(p[g] for g in GROUPS), cam, T_w_c)
        return (wC * C).sum() + (wD * D).sum() + (wA * A).sum()

    g = Gaussians.from_numpy(*(params[k] for k in GROUPS), device=device)
    views = Views.create([cam], T[None], device=device)
    out = render(g, views)
    grads = render_backward(g, views, out, wC[None], wD[None], wA[None])

    h = 1e-5
    for group in GROUPS:
        arr = params[group]
        fd = np.zeros(arr.shape)
        for idx in np.ndindex(arr.shape):
            plus, minus = {**params, group: arr.copy()}, {**params, group: arr.copy()}
            plus[group][idx] += h
            minus[group][idx] -= h
            fd[idx] = (loss(plus, T) - loss(minus, T)) / (2 * h)
        assert_grad_close(f"{model} {group}", getattr(grads, group).numpy().reshape(fd.shape), fd)
    fd_pose = np.array([(loss(params, T @ expm(hat(h * e))) - loss(params, T @ expm(hat(-h * e)))) / (2 * h) for e in np.eye(6)])
    assert_grad_close(f"{model} pose", grads.pose.numpy()[0], fd_pose)


@pytest.mark.parametrize("model", MODELS)
def test_projection_backward_matches_tape(model):
    """Warp's autodiff of the forward projection kernel agrees with the hand-written adjoint."""
    rng = np.random.default_rng(12)
    cam = cameras()[model]
    T = random_pose(rng)
    scene = random_scene(rng, 40, model, T)
    n = len(scene[0])
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    ins = [
        wp.array(f32(scene[0]), dtype=wp.vec3, requires_grad=True),
        wp.array(f32(scene[1]), dtype=wp.vec4, requires_grad=True),
        wp.array(f32(scene[2]), dtype=wp.vec3, requires_grad=True),
        wp.array(f32(scene[3]), dtype=float, requires_grad=True),
    ]
    cams = wp.array([cam], dtype=Camera)
    V = wp.array(f32(np.linalg.inv(T))[None], dtype=wp.mat44, requires_grad=True)
    outs = [
        wp.zeros(n, dtype=wp.vec2, requires_grad=True),
        wp.zeros(n, dtype=wp.vec3, requires_grad=True),
        wp.zeros(n, dtype=float, requires_grad=True),
        wp.zeros(n, dtype=float, requires_grad=True),
        wp.zeros(n, dtype=wp.int32),
    ]
    tape = wp.Tape()
    with tape:
        wp.launch(project_gaussians_kernel, dim=n, inputs=[*ins, cams, V, n, 0.01, 100.0], outputs=outs)
    out_grads = [
        wp.array(f32(rng.normal(size=(n, 2))), dtype=wp.vec2),
        wp.array(f32(rng.normal(size=(n, 3)) * 50), dtype=wp.vec3),
        wp.array(f32(rng.normal(size=n)), dtype=float),
        wp.array(f32(rng.normal(size=n)), dtype=float),
    ]
    tape.backward(grads=dict(zip(outs[:4], out_grads)))
    hand = [wp.zeros(n, dtype=d) for d in (wp.vec3, wp.vec4, wp.vec3, float)] + [wp.zeros(1, dtype=vec6)]
    wp.launch(
        project_gaussians_backward_kernel,
        dim=n,
        inputs=[*ins, cams, V, n, outs[4], outs[3], *out_grads],
        outputs=hand,
    )
    assert outs[4].numpy().sum() > 0.8 * n
    for name, a, b in zip(["means", "quats", "log_scales", "logits"], ins, hand[:4]):
        assert_grad_close(f"tape {model} {name}", b.numpy(), a.grad.numpy(), rtol=1e-4)
    # Tape gives dL/dV for V = T_c_w; T_w_c <- T_w_c Exp(xi) means V <- Exp(-xi) V.
    GV = V.grad.numpy()[0]
    Vm = V.numpy()[0]
    tape_pose = np.array([np.sum(GV * (-hat(e) @ Vm)) for e in np.eye(6)])
    assert_grad_close(f"tape {model} pose", hand[4].numpy()[0], tape_pose, rtol=1e-4)
