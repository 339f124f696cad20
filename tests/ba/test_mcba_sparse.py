"""MCBA's sparse Schur reduction on the device against the dense host reduction it replaced,
and against an independent float64 NumPy rebuild of the problem (end of the file).

The reference below is the earlier solver, kept here verbatim in spirit: it builds the
dense pose-depth coupling ``G`` [n,C,h*w,6n] on the host in float64, forms
``S = B - G^T Q G`` and ``rhs = v - G^T Q w`` with einsum, back-substitutes on the host and
updates the buffer there. The sparse path must give the same reduced system and the same
LM trajectory to float32 tolerance. The problem has several edges per view (temporal
radius 2 and cross-time edges, so two edges of one view can reach the same keyframe), cross-view edges, a
window that does not start at keyframe 0 (slots differ from buffer indices), and a
gauge that is not the window's first keyframe."""

import numpy as np
import pytest
import scipy.linalg
import warp as wp

from mcgs_warp.ba.edges import build_edges
from mcgs_warp.ba.mcba import MCBA, MCBAConfig
from mcgs_warp.geometry import matrix_to_transform7, se3_exp
from mcgs_warp.kernels.ba import mat66d, mcba_linearize_kernel, vec6d
from mcgs_warp.kernels.se3 import vec6
from problems import Problem

WINDOW = [1, 2, 3, 4]  # buffer keyframes 0..4; keyframe 0 stays outside the window


def make_problem(seq, seed=0):
    P = Problem(seq, [0, 2, 4, 6, 8])
    edges = build_edges(WINDOW, len(P.buf.rig), np.ones((3, 3)), radius=2, cross_view=True, cross_time=True)
    targets, weights = P.targets_for(edges)
    rng = np.random.default_rng(seed)
    targets = targets + rng.normal(scale=0.3, size=targets.shape)  # the optimum keeps a residual
    P.perturb(rng, trans=0.03, rot_deg=1.0, depth_noise=0.05)
    views = {(i, ci) for i, ci in edges[:, :2]}
    per_view = [np.sum((edges[:, 0] == i) & (edges[:, 1] == ci) & (edges[:, 0] != edges[:, 2])) for i, ci in views]
    assert min(per_view) >= 3 and np.any(edges[:, 0] == edges[:, 2])
    return P, edges, targets, weights


# ---- the earlier dense solver (reference) ----------------------------------------------
def dense_linearization(mcba, edges, targets, weights, keyframes, prior):
    """B [6n,6n], v [6n], G [n,C,h*w,6n], depth block and gradient with the prior [n,C,h*w],
    the depth block from the correspondences alone [n,C,h,w]; float64."""
    buf, cfg = mcba.buf, mcba.cfg
    slot = {k: s for s, k in enumerate(keyframes)}
    n, C, h, w, E = len(keyframes), len(buf.rig), buf.h, buf.w, len(edges)
    H = wp.zeros((E, 3), dtype=mat66d)
    g = wp.zeros((E, 2), dtype=vec6d)
    Epix = wp.zeros((E, h, w), dtype=vec6)
    Cd = wp.zeros((buf.capacity, C, h, w), dtype=float)
    wd = wp.zeros((buf.capacity, C, h, w), dtype=float)
    cost = wp.zeros(E, dtype=float)
    arrays = mcba._arrays(edges, targets, weights)
    inputs = [buf.rays, buf.disp, buf.poses, buf.T_b_c, buf.cameras, *arrays, cfg.huber_delta, 0]
    wp.launch(mcba_linearize_kernel, dim=(E, h, w), inputs=inputs, outputs=[H, g, Epix, Cd, wd, cost])
    Hn, gn = H.numpy().astype(np.float64), g.numpy().astype(np.float64)
    Ej = Epix.numpy().astype(np.float64).reshape(E, h * w, 6)  # pose j's couplings; pose i's: -Ad^T of them
    P = buf.get_poses()
    info = Cd.numpy()[keyframes].astype(np.float64)
    Cn = info.reshape(n, C, h * w)
    wn = wd.numpy()[keyframes].astype(np.float64).reshape(n, C, h * w)
    if prior is not None:
        disp_now = buf.disp.numpy()[keyframes].astype(np.float64).reshape(n, C, h * w)
        pw = cfg.prior_weight * prior[1].reshape(n, C, h * w)
        Cn = Cn + pw
        wn = wn + pw * (prior[0].reshape(n, C, h * w) - disp_now)
    B, v = np.zeros((6 * n, 6 * n)), np.zeros(6 * n)
    G = np.zeros((n, C, h * w, 6 * n))
    for e, (i, ci, j) in enumerate(edges[:, :3]):
        if i == j:
            continue
        si, sj = slot[i], slot[j]
        a, b = slice(6 * si, 6 * si + 6), slice(6 * sj, 6 * sj + 6)
        B[a, a] += Hn[e, 0]
        B[a, b] += Hn[e, 1]
        B[b, a] += Hn[e, 1].T
        B[b, b] += Hn[e, 2]
        v[a] += gn[e, 0]
        v[b] += gn[e, 1]
        T = np.linalg.inv(P[j]) @ P[i]
        Ad = np.zeros((6, 6))
        Ad[:3, :3] = Ad[3:, 3:] = T[:3, :3]
        Ad[:3, 3:] = np.cross(T[:3, 3], T[:3, :3].T).T  # [t]x R
        G[si, ci, :, a] += -Ej[e] @ Ad
        G[si, ci, :, b] += Ej[e]
    return B, v, G, Cn, wn, info


def depth_weight(Cn, lam):
    from mcgs_warp.kernels.ba import DEPTH_DAMPING

    return np.where(Cn > 0, 1.0 / (Cn * (1.0 + lam) + lam * DEPTH_DAMPING), 0.0)


def dense_schur(B, v, G, Cn, wn, lam):
    n = G.shape[0]
    Gf = G.reshape(-1, G.shape[2], G.shape[3])
    Q = depth_weight(Cn, lam).reshape(Gf.shape[:2])
    S = B - np.einsum("npa,np,npb->ab", Gf, Q, Gf, optimize=True)
    rhs = v - np.einsum("npa,np->a", Gf, Q * wn.reshape(Q.shape), optimize=True)
    assert S.shape == (6 * n, 6 * n)
    return S, rhs


def dense_solve(mcba, edges, targets, weights, keyframes, fixed):
    """The earlier ``MCBA.solve`` (host reduction, host state update): (costs, accepted, rejected, info)."""
    buf, cfg = mcba.buf, mcba.cfg
    n, C, h, w = len(keyframes), len(buf.rig), buf.h, buf.w
    arrays = mcba._arrays(edges, targets, weights)
    prior = tuple(x.numpy() for x in mcba.prior_target(keyframes)) if cfg.prior_weight > 0 else None

    def cost(disp=None, poses=None):
        total = mcba.cost(arrays, len(edges), disp=disp, poses=poses)
        if prior is not None:
            d = (buf.disp if disp is None else disp).numpy()[keyframes].astype(np.float64)
            total += 0.5 * cfg.prior_weight * float(np.sum(prior[1] * (prior[0] - d) ** 2))
        return total

    lam, current = cfg.lm_lambda, cost()
    costs, accepted, rejected, info = [current], 0, 0, None
    free = [s for s, k in enumerate(keyframes) if k not in fixed]
    free_idx = np.concatenate([np.arange(6 * s, 6 * s + 6) for s in free])
    for _ in range(cfg.iterations):
        B, v, G, Cn, wn, info = dense_linearization(mcba, edges, targets, weights, keyframes, prior)
        S, rhs = dense_schur(B, v, G, Cn, wn, lam)
        disp_now = buf.disp.numpy()[keyframes].astype(np.float64).reshape(n, C, h * w)
        while True:
            dxi = np.zeros(6 * n)
            Sf = S[np.ix_(free_idx, free_idx)]
            Sf = Sf + lam * np.diag(np.diag(Sf)) + 1e-9 * np.eye(len(free_idx))
            dxi[free_idx] = scipy.linalg.solve(Sf, rhs[free_idx], assume_a="sym")
            dd = depth_weight(Cn, lam) * (wn - np.einsum("ncpa,a->ncp", G, dxi))
            T = buf.get_poses()
            for s, k in enumerate(keyframes):
                T[k] = T[k] @ se3_exp(dxi[6 * s : 6 * s + 6])
            disp_all = buf.disp.numpy()
            cand = disp_all.copy()
            cand[keyframes] = np.maximum(disp_now + dd, cfg.min_disp).reshape(n, C, h, w).astype(np.float32)
            cand[keyframes] = np.where(disp_all[keyframes] > 0, cand[keyframes], 0.0)
            disp_c = wp.array(cand, dtype=float)
            poses_c = wp.clone(buf.poses)
            poses_c.assign(np.concatenate([matrix_to_transform7(T), buf.poses.numpy()[len(T) :]]).astype(np.float32))
            new_cost = cost(disp_c, poses_c)
            if new_cost <= current:
                buf.disp.assign(disp_c)
                buf.poses.assign(poses_c)
                current = new_cost
                costs.append(current)
                accepted += 1
                lam = max(lam / 3.0, 1e-9)
                break
            rejected += 1
            lam *= 4.0
            assert lam < 1e8
    return costs, accepted, rejected, info


def assert_close_mostly(got, want):
    """Equal to float32 tolerance, but for a few far, weakly observed depths (small C: the
    float32 rounding of the two paths moves them a little more) that stay within 0.3 %."""
    np.testing.assert_allclose(got, want, rtol=3e-3, atol=1e-6 * np.abs(want).max())
    close = np.isclose(got, want, rtol=1e-4, atol=1e-6 * np.abs(want).max())
    assert close.mean() > 0.999, close.mean()


# ---- tests -----------------------------------------------------------------------------
@pytest.mark.parametrize("prior_weight", [0.0, 0.5])
def test_sparse_schur_system_equals_the_dense_one(synthetic_seq, prior_weight):
    P, edges, targets, weights = make_problem(synthetic_seq)
    mcba = MCBA(P.buf, MCBAConfig(prior_weight=prior_weight))
    lam = 0.01
    S, rhs = mcba.reduced_system(edges, targets, weights, keyframes=WINDOW, lam=lam)
    prior = tuple(x.numpy() for x in mcba.prior_target(WINDOW)) if prior_weight > 0 else None
    B, v, G, Cn, wn, _ = dense_linearization(mcba, edges, targets, weights, WINDOW, prior)
    S_ref, rhs_ref = dense_schur(B, v, G, Cn, wn, lam)
    # The Schur parts alone (S - B, rhs - v), so that a wrong or missing block cannot hide
    # under the larger B: every 6x6 block of the window is filled.
    red, red_ref = S - B, S_ref - B
    assert np.all(np.abs(red_ref).reshape(4, 6, 4, 6).max((1, 3)) > 0)
    np.testing.assert_allclose(red, red_ref, rtol=1e-6, atol=1e-7 * np.abs(red_ref).max())  # float64 sums of float32 terms
    np.testing.assert_allclose(rhs - v, rhs_ref - v, rtol=1e-4, atol=1e-5 * np.abs(rhs_ref - v).max())
    np.testing.assert_allclose(S, S_ref, rtol=1e-4, atol=1e-5 * np.abs(S_ref).max())
    np.testing.assert_allclose(S, S.T, atol=1e-6 * np.abs(S).max())


@pytest.mark.parametrize("prior_weight", [0.0, 0.5])
def test_solve_follows_the_dense_solver(synthetic_seq, prior_weight):
    P, edges, targets, weights = make_problem(synthetic_seq, seed=1)
    buf = P.buf
    start = buf.disp.numpy().copy(), buf.poses.numpy().copy()
    cfg = MCBAConfig(iterations=4, prior_weight=prior_weight)
    costs, accepted, rejected, info = dense_solve(MCBA(buf, cfg), edges, targets, weights, WINDOW, fixed={3})
    want = buf.disp.numpy().copy(), buf.get_poses()
    buf.disp.assign(start[0])
    buf.poses.assign(start[1])
    stats = MCBA(buf, cfg).solve(edges, targets, weights, keyframes=WINDOW, fixed=[3])
    assert (stats.accepted, stats.rejected) == (accepted, rejected) and accepted >= 3
    assert stats.cost[-1] < 0.5 * stats.cost[0]
    np.testing.assert_allclose(stats.cost, costs, rtol=1e-5)
    assert stats.keyframes == WINDOW
    got = buf.get_poses()
    np.testing.assert_allclose(got, want[1], atol=1e-5)
    assert_close_mostly(buf.disp.numpy(), want[0])
    np.testing.assert_array_equal(buf.poses.numpy()[[0, 3]], start[1][[0, 3]])  # outside the window; the gauge
    np.testing.assert_array_equal(buf.disp.numpy()[0], start[0][0])
    assert_close_mostly(stats.depth_info.numpy(), info)


def test_reduced_system_and_cost_do_not_depend_on_the_cpu_thread_count(synthetic_seq, monkeypatch):
    """On the CPU the linearization, the cost and the Schur reduction run as bands of grid
    rows (or of edge pairs) on several threads, each summing its own per-edge terms: one
    thread and three give the same system and cost up to float summation order."""
    P, edges, targets, weights = make_problem(synthetic_seq, seed=2)
    mcba = MCBA(P.buf, MCBAConfig(prior_weight=0.5))
    out = {}
    for threads in ("1", "3"):
        monkeypatch.setenv("MCGS_WARP_CPU_THREADS", threads)
        S, rhs = mcba.reduced_system(edges, targets, weights, keyframes=WINDOW, lam=0.01)
        cost = mcba.cost(mcba._arrays(edges, targets, weights), len(edges))
        out[threads] = S, rhs, cost
    (S1, r1, c1), (S3, r3, c3) = out["1"], out["3"]
    assert np.abs(S1).max() > 0 and c1 > 0
    np.testing.assert_allclose(S3, S1, rtol=1e-5, atol=1e-6 * np.abs(S1).max())
    np.testing.assert_allclose(r3, r1, rtol=1e-5, atol=1e-6 * np.abs(r1).max())
    assert abs(c3 - c1) <= 1e-5 * c1, (c3, c1)


# ---- an independent reference: float64 NumPy reprojection, finite differences ------------
class NumpyReprojection:
    """MCBA's robust reprojection cost rebuilt from the float64 camera reference
    (``mcgs_warp.kernels.reference``, checked against OpenCV) and 4x4 matrices, with no code
    of the solver: residuals ``target - project(X_cj)`` of every edge pixel, Huber on
    ``sqrt(w) |r|``, pixels valid at the linearization point (in the camera's domain, within
    1 px of the image)."""

    def __init__(self, buf, edges, targets, weights, huber_delta):
        from mcgs_warp.kernels import reference

        self.ref, self.buf = reference, buf
        self.edges, self.targets = edges, targets.astype(np.float64)
        self.weights = np.where(np.isfinite(weights) & np.isfinite(targets).all(-1), weights, 0.0).astype(np.float64)
        self.cams = [c.warp_camera() for c in buf.reduced]
        self.T_b_c = [c.T_b_c for c in buf.rig.cameras]
        self.rays = buf.rays.numpy().astype(np.float64)
        self.delta = huber_delta

    def project(self, poses, disp):
        """Predicted pixels [E,h,w,2] and the in-domain mask [E,h,w] for poses [K,4,4], disp [K,C,h,w]."""
        uv = np.zeros(self.targets.shape)
        ok = np.zeros(self.weights.shape, bool)
        for e, (i, ci, j, cj) in enumerate(self.edges[:, :4]):
            d = disp[i, ci]
            X = self.rays[ci] / np.where(d > 0, d, 1.0)[..., None]
            M = np.linalg.inv(self.T_b_c[cj]) @ np.linalg.inv(poses[j]) @ poses[i] @ self.T_b_c[ci]
            Xj = X @ M[:3, :3].T + M[:3, 3]
            cam = self.cams[cj]
            uv[e] = self.ref.project(cam, Xj.reshape(-1, 3)).reshape(uv[e].shape)
            m = 1.0
            inside = (uv[e, ..., 0] >= -m) & (uv[e, ..., 1] >= -m) & (uv[e, ..., 0] <= cam.width - 1 + m) & (uv[e, ..., 1] <= cam.height - 1 + m)
            ok[e] = (d > 0) & self.ref.in_domain(cam, Xj.reshape(-1, 3)).reshape(d.shape) & inside
        return uv, ok & (self.weights > 0)

    def cost(self, poses, disp):
        uv, ok = self.project(poses, disp)
        s = np.sqrt(self.weights) * np.linalg.norm(self.targets - uv, axis=-1)
        c = np.where(s <= self.delta, 0.5 * s * s, self.delta * (s - 0.5 * self.delta))
        return float(c[ok].sum())

    def linearization(self, poses, disp, keyframes, step=1e-6):
        """Gauss-Newton blocks at (poses, disp) as MCBA defines them (IRLS Huber weights,
        poses perturbed on the right, ``T_w_b Exp(xi)``; inverse depth per pixel), with the
        Jacobians by central differences: B [6n,6n], v [6n], G [n,C,h*w,6n], C and w [n,C,h*w]."""
        from mcgs_warp.geometry import se3_exp

        slot = {k: s for s, k in enumerate(keyframes)}
        n, (E, h, w) = len(keyframes), self.weights.shape
        C = disp.shape[1]
        uv, ok = self.project(poses, disp)
        r = self.targets - uv
        s = np.sqrt(self.weights) * np.linalg.norm(r, axis=-1)
        W = np.where(ok, self.weights * np.where(s <= self.delta, 1.0, self.delta / np.maximum(s, 1e-300)), 0.0)
        J = np.zeros((E, h, w, 2, 6 * n))  # d uv / d xi
        for sl, k in enumerate(keyframes):
            for a in range(6):
                xi = np.zeros(6)
                xi[a] = step
                plus, minus = poses.copy(), poses.copy()
                plus[k], minus[k] = poses[k] @ se3_exp(xi), poses[k] @ se3_exp(-xi)
                J[..., 6 * sl + a] = (self.project(plus, disp)[0] - self.project(minus, disp)[0]) / (2 * step)
        dstep = 1e-6 * np.maximum(disp, 1e-3)
        Jd = (self.project(poses, disp + dstep)[0] - self.project(poses, disp - dstep)[0])  # each pixel moves only its own residuals
        Jd = Jd / (2 * np.stack([dstep[i, ci] for i, ci in self.edges[:, :2]]))[..., None]
        B, v = np.zeros((6 * n, 6 * n)), np.zeros(6 * n)
        G = np.zeros((n, C, h * w, 6 * n))
        Cd, wd = np.zeros((n, C, h * w)), np.zeros((n, C, h * w))
        for e, (i, ci, j) in enumerate(self.edges[:, :3]):
            We, Je, Jde, re = W[e].reshape(-1), J[e].reshape(h * w, 2, -1), Jd[e].reshape(h * w, 2), r[e].reshape(h * w, 2)
            Cd[slot[i], ci] += We * np.einsum("pa,pa->p", Jde, Jde)
            wd[slot[i], ci] += We * np.einsum("pa,pa->p", Jde, re)
            if i == j:
                continue
            B += np.einsum("p,pax,pay->xy", We, Je, Je)
            v += np.einsum("p,pax,pa->x", We, Je, re)
            G[slot[i], ci] += We[:, None] * np.einsum("pax,pa->px", Je, Jde)
        return B, v, G, Cd, wd


@pytest.mark.parametrize("prior_weight", [0.0, 0.5])
def test_reduced_system_matches_an_independent_numpy_reference(synthetic_seq, prior_weight):
    """The sparse device reduction and the cost against a float64 NumPy rebuild of the
    problem that shares no solver code (only the camera reference model and the grid rays):
    the cost is the same, and the reduced camera system S and its right-hand side equal the
    Schur complement of finite-difference Gauss-Newton blocks."""
    P, edges, targets, weights = make_problem(synthetic_seq, seed=3)
    mcba = MCBA(P.buf, MCBAConfig(prior_weight=prior_weight))
    buf, lam = P.buf, 0.01
    ref = NumpyReprojection(buf, edges, targets, weights, mcba.cfg.huber_delta)
    poses, disp = buf.get_poses().astype(np.float64), buf.disp.numpy().astype(np.float64)
    assert mcba.cost(mcba._arrays(edges, targets, weights), len(edges)) == pytest.approx(ref.cost(poses, disp), rel=1e-4)
    B, v, G, Cd, wd = ref.linearization(poses, disp, WINDOW)
    if prior_weight > 0:  # the inverse-depth prior 0.5 pw m (target - d)^2 of every window pixel
        target, mask = (x.numpy().astype(np.float64).reshape(Cd.shape) for x in mcba.prior_target(WINDOW))
        Cd = Cd + prior_weight * mask
        wd = wd + prior_weight * mask * (target - disp[WINDOW].reshape(Cd.shape))
    S_ref, rhs_ref = dense_schur(B, v, G, Cd, wd, lam)
    S, rhs = mcba.reduced_system(edges, targets, weights, keyframes=WINDOW, lam=lam)
    scale_S, scale_r = np.abs(S_ref).max(), np.abs(rhs_ref).max()
    assert scale_S > 0 and scale_r > 0
    # measured: 2e-7 (S), 6e-7 (rhs) of their largest entry, 2e-6 for the Schur part alone
    np.testing.assert_allclose(S, S_ref, atol=1e-5 * scale_S)
    np.testing.assert_allclose(rhs, rhs_ref, atol=1e-5 * scale_r)
    np.testing.assert_allclose(S - B, S_ref - B, atol=1e-4 * np.abs(S_ref - B).max())
