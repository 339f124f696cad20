"""Joint Depth-Scale Alignment (JDSA, paper eq. 5, after HI-SLAM2).

Each keyframe view carries an ``m x n`` grid of scales ``s`` whose bilinear
interpolation ``B(p, s)`` rescales its depth prior: ``d~(p) = d+(p) B(p, s)``. JDSA
alternates two steps and never solves poses and scales jointly:

1. MCBA with the scaled prior as an inverse-depth prior (see :class:`MCBA`);
2. per view, the scales that best align the scaled prior with the optimized depth,
   ``min_s sum_p w(p) (d+(p) B(p, s) - d(p))^2 + lam |s - s_now|^2``, a small linear
   least-squares problem (B is linear in s; the tiny Tikhonov term, :func:`tikhonov_solve`,
   keeps grid nodes without data where they are).

Grid nodes sit on the image corners and spread evenly between them.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

#: the range a scale node may take: a prior off by more than 4x either way is not one to rescale.
#: Without it a node that few weighted pixels see can swing through zero (a negative depth,
#: which the prior then drops) and the mean-log hold below would divide by log(0).
SCALE_RANGE = (0.25, 4.0)


@lru_cache(maxsize=32)
def bilinear_basis(m: int, n: int, h: int, w: int) -> np.ndarray:
    """Weights [h*w, m*n] so that ``basis @ s.ravel()`` is the bilinear field on an h x w grid."""
    ys = np.linspace(0, m - 1, h) if m > 1 else np.zeros(h)
    xs = np.linspace(0, n - 1, w) if n > 1 else np.zeros(w)
    y0 = np.minimum(np.floor(ys).astype(int), max(m - 2, 0))
    x0 = np.minimum(np.floor(xs).astype(int), max(n - 2, 0))
    fy, fx = ys - y0, xs - x0
    basis = np.zeros((h, w, m, n))
    Y, X = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            yy = np.minimum(y0 + dy, m - 1)
            xx = np.minimum(x0 + dx, n - 1)
            np.add.at(basis, (Y, X, yy[Y], xx[X]), wy[Y] * wx[X])
    return basis.reshape(h * w, m * n)


def scale_field(scales: np.ndarray, h: int, w: int) -> np.ndarray:
    """Per-pixel scale [h,w] of an m x n grid."""
    m, n = scales.shape
    return (bilinear_basis(m, n, h, w) @ scales.ravel()).reshape(h, w)


def solve_scales(depth_prior: np.ndarray, depth: np.ndarray, grid_shape=(4, 6), weight=None, reg: float = 1e-6, start=None) -> np.ndarray:
    """Scale grid aligning ``depth_prior * B(p, s)`` to ``depth`` ([h,w], m; 0 = unknown).
    A small Tikhonov term pulls toward ``start`` (the current grid; default 1), so grid
    nodes without data keep their value."""
    m, n = grid_shape
    h, w = depth.shape
    Phi = bilinear_basis(m, n, h, w)
    valid = ((depth_prior > 0) & (depth > 0)).ravel()
    wts = np.ones(h * w) if weight is None else np.asarray(weight, dtype=np.float64).ravel()
    wts = wts * valid
    A = Phi * depth_prior.ravel()[:, None]
    AtA = A.T @ (A * wts[:, None])
    Atb = A.T @ (wts * depth.ravel())
    s0 = np.ones(m * n) if start is None else np.asarray(start, np.float64).ravel()
    return tikhonov_solve(AtA, Atb, s0, reg).reshape(m, n)


def tikhonov_solve(AtA: np.ndarray, Atb: np.ndarray, start: np.ndarray, reg: float) -> np.ndarray:
    """``s`` [mn] from the normal equations with ``lam |s - start|^2`` added, ``lam = reg``
    times the mean diagonal of ``AtA`` (relative, so independent of depth units and weights)."""
    lam = reg * (np.trace(AtA) / len(Atb) + 1e-12)
    return np.linalg.solve(AtA + lam * np.eye(len(Atb)), Atb + lam * np.ravel(start))


def scaled_prior(buffer, keyframes) -> tuple:
    """MCBA's inverse-depth prior for ``keyframes`` (window slots in that order), on the
    buffer's device: ``(target, mask)`` [n,C,h,w] float, ``target = 1 / (d+ B(p, s))`` (1/m,
    0 = none) and ``mask`` the prior's confidence where it has depth (else 0)."""
    import warp as wp

    from ..kernels.ba import scaled_prior_kernel

    dev, C = buffer.device, len(buffer.rig)
    shape = (len(keyframes), C, buffer.h, buffer.w)
    kf = wp.array(np.asarray(keyframes, dtype=np.int32), dtype=wp.int32, device=dev)
    target, mask = wp.empty(shape, dtype=float, device=dev), wp.empty(shape, dtype=float, device=dev)
    if len(keyframes):
        wp.launch(scaled_prior_kernel, dim=shape, inputs=[buffer.depth_prior, buffer.prior_conf, buffer.scales, kf], outputs=[target, mask], device=dev)
    return target, mask


def update_scales(buffer, keyframes, stats=None, hold_mean: bool = False, reg: float = 1e-6) -> None:
    """JDSA step 2: re-fit every view's scale grid to its current MCBA depth.

    With ``stats`` (the :class:`~mcgs_warp.ba.mcba.MCBAStats` of the last solve) each pixel
    is weighted by the inverse variance of its MCBA depth from the correspondences,
    ``info * rho^4`` (``stats.depth_info``, MCBA's depth block of its last linearization;
    0 for a keyframe the solve did not see), times the prior's confidence: pixels whose
    depth only echoes the prior, or that lack parallax (far, near the epipole), carry no
    scale information. Fitting to them lets the prior drag the metric scale (the drift
    HI-SLAM2 and the paper warn about). Without ``stats`` every pixel with a prior and a
    depth counts with the prior's confidence. A view with no weight keeps its grid.

    The normal equations are reduced on the device (:func:`~mcgs_warp.kernels.ba.jdsa_normal_kernel`);
    only the ``(m n) x (m n)`` system of each fitted view and its grid cross to the host
    (:func:`tikhonov_solve`, towards the current grid, as :func:`solve_scales`).

    ``hold_mean``: the fit may not change the mean log scale of the grids it moves (they
    are divided by the change). Without correspondences that measure metric depth (no
    overlapping rig cameras), MCBA's depth has the prior's scale only: scaling depths,
    translations and scale grids together changes almost no residual (only the rig's
    lever arms, under rotation, see it), so a free fit lets the metric scale wander
    (front+back rig, mono prior, seed 1: Sim(3) scale 1.019, SE(3) ATE 32 mm against 1.005
    and 10 mm without JDSA). Holding the mean keeps the
    prior's scale on average and leaves JDSA the views' relative scales."""
    import warp as wp

    from ..kernels.ba import jdsa_normal_kernel

    dev, C = buffer.device, len(buffer.rig)
    m, n = buffer.scales.shape[2:]
    mn = m * n
    slot_of = {int(k): s for s, k in enumerate(stats.keyframes)} if stats is not None and stats.depth_info is not None else {}
    # with stats, a keyframe the solve did not see has information 0 there: its grids stay
    fitted = [int(k) for k in keyframes if stats is None or int(k) in slot_of]
    if not fitted:
        return
    V = len(fitted)
    info = stats.depth_info if slot_of else wp.zeros((1, C, 1, 1), dtype=float, device=dev)
    slots = [slot_of.get(k, -1) for k in fitted]  # -1: the kernel weighs by confidence alone
    AtA = wp.zeros((V, C, mn, mn), dtype=wp.float64, device=dev)
    Atb = wp.zeros((V, C, mn), dtype=wp.float64, device=dev)
    wsum = wp.zeros((V, C), dtype=wp.float64, device=dev)
    kf = wp.array(np.asarray(fitted, dtype=np.int32), dtype=wp.int32, device=dev)
    sl = wp.array(np.asarray(slots, dtype=np.int32), dtype=wp.int32, device=dev)
    wp.launch(jdsa_normal_kernel, dim=(V, C, buffer.h, buffer.w), inputs=[buffer.depth_prior, buffer.prior_conf, buffer.disp, info, kf, sl, m, n], outputs=[AtA, Atb, wsum], device=dev)
    AtA, Atb, wsum = AtA.numpy(), Atb.numpy(), wsum.numpy()
    old = np.stack([buffer.scales[k].numpy() for k in fitted]).astype(np.float64)  # [V,C,m,n]
    new = old.copy()
    solved = wsum > 0  # [V,C]; a view with no weight (nothing measured) keeps its grid
    for v, c in zip(*np.nonzero(solved)):
        new[v, c] = np.clip(tikhonov_solve(AtA[v, c], Atb[v, c], old[v, c], reg).reshape(m, n), *SCALE_RANGE)
    if hold_mean and solved.any():
        # the mean over the grids this fit moved: untouched grids must not dilute the hold
        shift = np.log(new[solved]).mean() - np.log(np.clip(old[solved], *SCALE_RANGE)).mean()
        new[solved] = np.clip(new[solved] * np.exp(-shift), *SCALE_RANGE)
    for v, k in enumerate(fitted):
        if solved[v].any():
            buffer.scales[k].assign(new[v])


def mcba_with_jdsa(mcba, edges, targets, weights, keyframes=None, rounds: int = 3, fixed=None, hold_mean: bool = False, keypoints=None, factors=(), config=None):
    """Alternate MCBA (with the scaled prior) and the scale update, ``rounds`` times
    (``hold_mean``: see :func:`update_scales`; ``config``: the solves' MCBAConfig, default the solver's)."""
    stats = []
    if keyframes is None:
        keyframes = np.unique(np.concatenate([edges[:, 0], edges[:, 2]]))
    for _ in range(rounds):
        stats.append(mcba.solve(edges, targets, weights, keyframes=keyframes, fixed=fixed, keypoints=keypoints, factors=factors, config=config))
        update_scales(mcba.buf, keyframes, stats[-1], hold_mean=hold_mean)
    return stats
