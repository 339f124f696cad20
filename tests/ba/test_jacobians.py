"""The MCBA kernel's assembled blocks against float64 central differences of the residual.

The residual is recomputed in NumPy from the same unit-depth rays, so the only
difference between the two is the Jacobians (and float32 rounding in the kernel)."""

import numpy as np
import pytest
import warp as wp

from mcgs_warp.buffer import KeyframeBuffer
from mcgs_warp.geometry import se3_exp
from mcgs_warp.kernels import reference
from mcgs_warp.kernels.ba import mat66d, mcba_linearize_kernel, vec6d
from mcgs_warp.kernels.se3 import vec6
from mcgs_warp.rig import CameraSpec, Rig

MODELS = {
    "pinhole": dict(intrinsics=(60.0, 62.0, 31.5, 23.5), distortion=(-0.1, 0.02, 0.001, -0.001, 0.0)),
    "fisheye": dict(intrinsics=(40.0, 40.0, 32.0, 24.0), distortion=(0.03, -0.01, 0.002, 0.0)),
    "equirectangular": dict(intrinsics=None, distortion=()),
}


def make_rig(model, yaw=0.35):
    Tb = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    Tb[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    Tb[:3, 3] = [0.3, -0.05, 0.1]
    kw = MODELS[model]
    return Rig([CameraSpec("a", model, 64, 48, kw["intrinsics"], kw["distortion"]), CameraSpec("b", model, 64, 48, kw["intrinsics"], kw["distortion"], Tb)])


def predict(buf, edge, rays, disp, poses):
    cams = [c.warp_camera() for c in buf.reduced]
    """Predicted pixels [P,2] in view (j, cj) and whether the kernel keeps them."""
    i, ci, j, cj = edge
    T_b_c = [c.T_b_c for c in buf.rig.cameras]
    X = rays[ci] / disp[i, ci][..., None]
    T = np.linalg.inv(poses[j] @ T_b_c[cj]) @ poses[i] @ T_b_c[ci]
    Xj = X.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    cam = cams[cj]
    ok = reference.in_domain(cam, Xj, 0.01, 1000.0)
    uv = reference.project(cam, np.where(ok[:, None], Xj, [0, 0, 1.0]))
    ok &= (uv[:, 0] >= -1) & (uv[:, 1] >= -1) & (uv[:, 0] <= cam.width) & (uv[:, 1] <= cam.height)
    return uv, ok


def residuals(buf, edge, rays, disp, poses, targets):
    return targets.reshape(-1, 2) - predict(buf, edge, rays, disp, poses)[0]


@pytest.mark.parametrize("model", list(MODELS))
def test_blocks_match_finite_differences(model):
    rng = np.random.default_rng(3)
    rig = make_rig(model)
    buf = KeyframeBuffer(rig, stride=8, capacity=3)
    h, w = buf.h, buf.w
    poses = np.stack([np.eye(4), se3_exp([0.2, 0.05, 0.1, 0.03, -0.08, 0.02])])
    disp = rng.uniform(0.15, 0.4, (2, 2, h, w))
    for k in range(2):
        buf.add(k, k, [None, None], poses[k], disp[k].astype(np.float32))
    disp = buf.disp.numpy()[:2].astype(np.float64)  # exactly what the kernel sees
    poses = buf.get_poses()
    rays = buf.rays.numpy().astype(np.float64)
    edges = np.array([[0, 0, 1, 0], [0, 1, 1, 0], [1, 0, 1, 1]], dtype=np.int32)  # temporal, cross-time, cross-view
    targets = np.zeros((len(edges), h, w, 2))
    for e, edge in enumerate(edges):
        targets[e] = (-residuals(buf, edge, rays, disp, poses, np.zeros((h, w, 2)))).reshape(h, w, 2)
    targets += rng.normal(scale=0.5, size=targets.shape)
    weights = rng.uniform(0.2, 1.0, (len(edges), h, w))

    E = len(edges)
    H = wp.zeros((E, 3), dtype=mat66d)
    g = wp.zeros((E, 2), dtype=vec6d)
    Epix = wp.zeros((E, h, w), dtype=vec6)
    Cd = wp.zeros((3, 2, h, w), dtype=float)
    wd = wp.zeros((3, 2, h, w), dtype=float)
    cost = wp.zeros(E, dtype=float)
    wp.launch(
        mcba_linearize_kernel,
        dim=(E, h, w),
        inputs=[
            buf.rays, buf.disp, buf.poses, buf.T_b_c, buf.cameras,
            wp.array(edges, dtype=wp.vec4i), wp.array(targets.astype(np.float32), dtype=wp.vec2),
            wp.array(weights.astype(np.float32), dtype=float), 1e6, 0,
        ],
        outputs=[H, g, Epix, Cd, wd, cost],
    )  # fmt: skip
    H, g, Epix, Cd, wd = H.numpy(), g.numpy(), Epix.numpy(), Cd.numpy(), wd.numpy()

    C_fd = np.zeros((2, 2, h, w))
    w_fd = np.zeros((2, 2, h, w))
    for e, edge in enumerate(edges):
        i, ci, j, cj = edge
        r0 = residuals(buf, edge, rays, disp, poses, targets[e])
        valid = predict(buf, edge, rays, disp, poses)[1]
        assert valid.mean() > 0.3
        W = weights[e].reshape(-1) * valid
        # d prediction / d parameter = -d r / d parameter
        Jpose = []
        for k in (i, j):
            cols = []
            for a in range(6):
                step = np.zeros(6)
                step[a] = 1e-6
                Pp, Pm = poses.copy(), poses.copy()
                Pp[k] = Pp[k] @ se3_exp(step)
                Pm[k] = Pm[k] @ se3_exp(-step)
                cols.append(-(residuals(buf, edge, rays, disp, Pp, targets[e]) - residuals(buf, edge, rays, disp, Pm, targets[e])) / 2e-6)
            Jpose.append(np.stack(cols, -1))  # [P,2,6]
        dp, dm = disp.copy(), disp.copy()
        dp[i, ci] += 1e-7
        dm[i, ci] -= 1e-7
        Jd = -(residuals(buf, edge, rays, dp, poses, targets[e]) - residuals(buf, edge, rays, dm, poses, targets[e])) / 2e-7
        C_fd[i, ci] += (W * (Jd**2).sum(1)).reshape(h, w)
        w_fd[i, ci] += (W * (Jd * r0).sum(1)).reshape(h, w)
        if i == j:
            assert not H[e].any() and not Epix[e].any(), "cross-view edges carry no pose terms"
            continue
        Ji, Jj = Jpose
        for blk, (A, B) in enumerate([(Ji, Ji), (Ji, Jj), (Jj, Jj)]):
            want = np.einsum("p,pka,pkb->ab", W, A, B)
            np.testing.assert_allclose(H[e, blk], want, rtol=2e-3, atol=2e-3 * np.abs(want).max())
        # the kernel stores pose j's couplings; pose i's are -Ad^T of them (Ad of T_bj_bi)
        T = np.linalg.inv(poses[j]) @ poses[i]
        R, t = T[:3, :3], T[:3, 3]
        Ad = np.zeros((6, 6))
        Ad[:3, :3] = Ad[3:, 3:] = R
        Ad[:3, 3:] = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
        couplings = [-Epix[e].astype(np.float64) @ Ad, Epix[e]]
        for blk, A in enumerate([Ji, Jj]):
            want = np.einsum("p,pka,pk->a", W, A, r0)
            np.testing.assert_allclose(g[e, blk], want, rtol=2e-3, atol=2e-3 * np.abs(want).max())
            want_E = np.einsum("p,pka,pk->pa", W, A, Jd).reshape(h, w, 6)
            np.testing.assert_allclose(couplings[blk], want_E, rtol=2e-3, atol=2e-3 * np.abs(want_E).max())
    np.testing.assert_allclose(Cd[:2], C_fd, rtol=2e-3, atol=2e-3 * C_fd.max())
    np.testing.assert_allclose(wd[:2], w_fd, rtol=2e-3, atol=2e-3 * np.abs(w_fd).max())
    assert C_fd.max() > 0 and np.abs(H[0, 0]).max() > 0
