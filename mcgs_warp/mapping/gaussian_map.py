"""The 3D Gaussian map: parameters on a Warp device plus, per Gaussian, its anchor keyframe and
whether a measurement put it where it is.

New Gaussians come from back-projected keyframe depth (every ``stride``-th pixel),
coloured from the image, isotropic with a scale of half their footprint: the ``stride``
pixels between samples at their range, ``0.5 stride r / f`` (``f`` the camera's pixels per
radian), so neighbouring splats meet at about one sigma at any depth, resolution and field
of view, whatever else the map holds there; unit rotation and opacity 0.9 (a Gaussian
seeded where no depth was measured, at its neighbourhood's depth, starts fainter). Each
Gaussian remembers the keyframe it was created from, so when tracking moves that
keyframe its Gaussians move with it (paper eq. 12-13), and whether it was seeded at a
measured depth (a depth target: sensor, rig stereo, the MCBA depth, multi-view consistent)
or at a guessed one (the fill); a guessed Gaussian becomes measured once a view's depth target
agrees with it (:meth:`Mapper.densify_and_prune`). Clones and split children inherit it; the
renderer turns it into a per-pixel confidence (:meth:`Mapper.depth_confidence`).

The map also owns its densification: per Gaussian, the sum over mapping steps and
views of ``|dL/d mean2d|`` and the number of views that saw it (device float64 arrays);
:meth:`GaussianMap.densify_and_prune` clones small and splits large Gaussians whose
mean view-space gradient is large, and prunes near-transparent and oversized ones (the
3DGS adaptive density control). Every change of the Gaussians' order or number
returns or follows an index (new -> old, -1 = new) so that optimizer state can follow.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import Gaussians

INITIAL_OPACITY = 0.9
MAX_INITIAL_SCALE = 0.5  # m


def logit(p):
    return np.log(p / (1.0 - p))


@dataclass
class DensifyReport:
    cloned: int = 0
    split: int = 0
    pruned: int = 0  # all pruned Gaussians, of which
    floaters: int = 0  # ... in front of the keyframes' depth (Mapper.view_statistics)
    oversized_on_screen: int = 0  # ... wider than the screen budget in some keyframe view


class GaussianMap:
    def __init__(self, device=None):
        self.device = wp.get_device(device)
        self.gaussians = Gaussians.from_numpy(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), self.device)
        self.anchors = np.zeros(0, np.int32)  # keyframe id per Gaussian
        self.measured = np.zeros(0, bool)  # per Gaussian: seeded at (or since confirmed by) a measured depth; False: its depth was guessed
        self._anchors_dev = None
        self.grad_accum = wp.zeros(0, dtype=wp.float64, device=self.device)  # [N] sum of |dL/d mean2d| over steps and views
        self.grad_count = wp.zeros(0, dtype=wp.float64, device=self.device)  # [N] views that saw it

    def __len__(self) -> int:
        return self.gaussians.n

    # ----------------------------------------------------------------------------------
    def to_numpy(self) -> dict:
        g = self.gaussians
        return {
            "means": g.means.numpy().copy(),
            "quats": g.quats.numpy().copy(),
            "log_scales": g.log_scales.numpy().copy(),
            "opacity_logits": g.opacity_logits.numpy().copy(),
            "colors": g.colors.numpy().copy(),
            "anchors": self.anchors.copy(),
            "measured": self.measured.copy(),
        }

    def set_numpy(self, d: dict, index: np.ndarray | None = None) -> None:
        """Replace the Gaussians by ``d`` (as :meth:`to_numpy` gives). With ``index``
        ([N_new], source Gaussian or -1) the densification statistics follow; without,
        they restart at zero. Without ``measured`` (a map from an older file) no Gaussian counts as measured."""
        stats = self.statistics() if index is not None and self.grad_accum.shape[0] == len(self) else None
        self.gaussians = Gaussians.from_numpy(d["means"], d["quats"], d["log_scales"], d["opacity_logits"], d["colors"], self.device)
        self.anchors = np.asarray(d["anchors"], np.int32)
        self._anchors_dev = None
        n = len(self)
        self.measured = np.asarray(d["measured"], bool).reshape(n) if d.get("measured") is not None else np.zeros(n, bool)
        acc, cnt = np.zeros(n), np.zeros(n)
        if stats is not None:
            ok = index >= 0
            acc[ok], cnt[ok] = stats[0][index[ok]], stats[1][index[ok]]
        self.set_statistics(acc, cnt)

    def statistics(self) -> tuple[np.ndarray, np.ndarray]:
        """Host copies of the densification statistics: (sum of |dL/d mean2d| [N], view count [N])."""
        return self.grad_accum.numpy().copy(), self.grad_count.numpy().copy()

    def set_statistics(self, accum, count) -> None:
        """Set the densification statistics ([N] each, float64)."""
        self.grad_accum = wp.array(np.asarray(accum, np.float64), dtype=wp.float64, device=self.device)
        self.grad_count = wp.array(np.asarray(count, np.float64), dtype=wp.float64, device=self.device)

    def accumulate_view_gradients(self, mean2d_grads: wp.array, visible: wp.array, n_views: int) -> None:
        """Add one step's ``|dL/d mean2d|`` ([C*N] vec2, as ``Gradients.mean2d``) and
        visibility ([C*N] int32) over its ``n_views`` views to the statistics."""
        from ..kernels.mapping import view_gradient_stats_kernel

        if len(self) == 0:
            return
        if self.grad_accum.shape[0] != len(self):  # the Gaussians were replaced without set_numpy
            self.set_statistics(np.zeros(len(self)), np.zeros(len(self)))
        wp.launch(view_gradient_stats_kernel, dim=len(self), inputs=[mean2d_grads, visible, len(self), int(n_views)], outputs=[self.grad_accum, self.grad_count], device=self.device)

    def append(self, means, colors, log_scales, anchor: int, quats=None, opacity_logits=None, measured=True) -> int:
        """Add ``n`` Gaussians (means [n,3] world m, colours [n,3], log-scales [n,3]; unit
        rotation and the initial opacity unless given) anchored to keyframe ``anchor``;
        ``measured`` (bool or [n]): placed at a measured depth."""
        n = len(means)
        quats = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)) if quats is None else quats
        opacity_logits = np.full(n, logit(INITIAL_OPACITY)) if opacity_logits is None else opacity_logits
        d = self.to_numpy()
        new = {"means": means, "quats": quats, "log_scales": log_scales, "opacity_logits": opacity_logits, "colors": colors, "anchors": np.full(n, anchor, np.int32), "measured": np.broadcast_to(np.asarray(measured, bool), (n,))}
        before = len(self)
        self.set_numpy({k: np.concatenate([d[k], np.asarray(new[k], dtype=d[k].dtype)]) for k in d}, np.concatenate([np.arange(before), -np.ones(n, int)]))
        return n

    def keep(self, mask: np.ndarray) -> int:
        """Keep the Gaussians where ``mask`` is true; returns how many were removed."""
        d = self.to_numpy()
        self.set_numpy({k: v[mask] for k, v in d.items()}, np.nonzero(mask)[0])
        return int((~mask).sum())

    def densify_and_prune(self, grad_threshold: float, split_scale: float, prune_opacity: float, prune_scale: float, max_gaussians: int, rng, drop=None) -> tuple[DensifyReport, np.ndarray]:
        """Adaptive density control from the accumulated statistics, which then restart.

        Prune Gaussians with opacity below ``prune_opacity``, largest scale above
        ``prune_scale`` (m) or ``drop`` ([N] bool: what the views rule out, e.g. floaters). Of the others, those whose mean ``|dL/d mean2d|`` per view
        exceeds ``grad_threshold`` (at most ``max_gaussians`` in all) are cloned when
        their largest scale is at most ``split_scale`` (m), else split in two children
        sampled from the Gaussian (``rng``: NumPy generator) with scales / 1.6.
        Returns the report and the index [N_new] of each new Gaussian's source (-1 = new)."""
        d = self.to_numpy()
        n = len(d["means"])
        report = DensifyReport()
        if n == 0:
            return report, np.zeros(0, int)
        accum, count = self.statistics()
        mean_grad = accum / np.maximum(count, 1)
        scale = np.exp(d["log_scales"]).max(1)
        opacity = 1 / (1 + np.exp(-d["opacity_logits"]))
        keep = (opacity >= prune_opacity) & (scale <= prune_scale)
        if drop is not None:
            keep &= ~np.asarray(drop, bool)
        report.pruned = int((~keep).sum())
        hot = keep & (mean_grad > grad_threshold)
        room = max(max_gaussians - int(keep.sum()), 0)
        hot_idx = np.nonzero(hot)[0][:room]
        clone = hot_idx[scale[hot_idx] <= split_scale]
        split = hot_idx[scale[hot_idx] > split_scale]
        report.cloned, report.split = len(clone), len(split)
        index = [np.nonzero(keep & ~np.isin(np.arange(n), split))[0], clone]
        new = {key: [v[index[0]], v[clone]] for key, v in d.items()}
        if len(split):
            from ..geometry import quat_to_matrix

            R = quat_to_matrix(d["quats"][split])
            s = np.exp(d["log_scales"][split])
            for _ in range(2):
                offset = np.einsum("nij,nj->ni", R, rng.normal(size=s.shape) * s)
                for key, v in d.items():
                    val = v[split]
                    if key == "means":
                        val = val + offset
                    elif key == "log_scales":
                        val = val - np.log(1.6)
                    new[key].append(val)
                index.append(-np.ones(len(split), int))
        self.set_numpy({key: np.concatenate(parts) for key, parts in new.items()})  # statistics restart
        return report, np.concatenate(index)

    # ----------------------------------------------------------------------------------
    def insert_from_depth(self, rig, T_w_b, images, depths, anchor: int, stride: int = 4, mask=None, max_depth: float = 50.0, fill: bool = False, fill_opacity: float = INITIAL_OPACITY) -> int:
        """Back-project every ``stride``-th pixel with depth of each camera (``mask[c]``
        [H,W] bool limits to unobserved pixels) into new Gaussians anchored to ``anchor``,
        sized by their footprint (module docstring). With ``fill``, the masked pixels
        without a depth target take the depth their neighbourhood has (:func:`fill_depth`):
        every pixel the mask allows gets a Gaussian, left to the photometric loss; those
        start at ``fill_opacity`` (faint: a guessed depth must not hide what other views
        measured until the colour loss wants it)."""
        from ..ba.edges import unproject_pixels

        pts, cols, sizes, guessed = [], [], [], []
        for c, spec in enumerate(rig.cameras):
            d = depths[c]
            if d is None:
                continue
            measured = (d > 0) & (d < max_depth)
            if fill:
                d = fill_depth(np.where(measured, d, 0.0))
            o = stride // 2
            v, u = np.mgrid[o : spec.height : stride, o : spec.width : stride]
            z = d[v, u]
            ok = (z > 0) & (z < max_depth)
            if mask is not None and mask[c] is not None:
                ok &= mask[c][v, u]
            if not ok.any():
                continue
            uv = np.stack([u[ok], v[ok]], 1).astype(np.float64)
            X_c = unproject_pixels(spec.warp_camera(), uv) * z[ok][:, None]
            has_ray = np.isfinite(X_c).all(1)  # NaN: a pixel without a ray (beyond a fisheye's 90 degrees)
            T = T_w_b @ spec.T_b_c
            pts.append(X_c[has_ray] @ T[:3, :3].T + T[:3, 3])
            cols.append(images[c][v[ok], u[ok]][has_ray])
            sizes.append(stride * np.linalg.norm(X_c[has_ray], axis=1) / spec.pixels_per_radian)
            guessed.append(~measured[v[ok], u[ok]][has_ray])
        if not pts:
            return 0
        pts = np.concatenate(pts)
        cols = np.concatenate(cols)
        scale = np.clip(0.5 * np.concatenate(sizes), 1e-4, MAX_INITIAL_SCALE)
        guessed = np.concatenate(guessed)
        opacity = np.where(guessed, fill_opacity, INITIAL_OPACITY)
        return self.append(pts, cols, np.log(np.repeat(scale[:, None], 3, 1)), anchor, opacity_logits=logit(opacity), measured=~guessed)

    def anchors_device(self) -> wp.array:
        """The anchors on the device (made on first use after the map changed)."""
        if self._anchors_dev is None:
            self._anchors_dev = wp.array(self.anchors, dtype=wp.int32, device=self.device)
        return self._anchors_dev

    def move_anchored(self, keyframe: int, delta: np.ndarray, scale: float = 1.0) -> None:
        """Eq. 12-13: apply the world-frame correction ``delta`` (4x4, x <- delta x) to the
        Gaussians anchored to ``keyframe``; multiply their scales by ``scale``."""
        from ..kernels.mapping import move_anchored_kernel

        if len(self) == 0:
            return
        g = self.gaussians
        wp.launch(
            move_anchored_kernel,
            dim=len(self),
            inputs=[g.means, g.quats, g.log_scales, self.anchors_device(), int(keyframe), wp.mat44(*np.asarray(delta, np.float32).ravel()), float(np.log(scale))],
            device=self.device,
        )

    def follow_depth(self, keyframe: int, T_w_b: np.ndarray, rig, cameras, ratio: np.ndarray) -> None:
        """Eq. 13 per pixel: the Gaussians anchored to ``keyframe`` (rig pose ``T_w_b``) follow
        a change of its depth, ``ratio`` [C,h,w] = new / old depth on the grid of ``cameras``
        (a Warp array of the rig's cameras at that grid's resolution): each moves along the
        ray of the camera that sees it nearest its image centre, its size scales alike."""
        from ..geometry import matrix_to_transform7
        from ..kernels.mapping import follow_depth_kernel

        if len(self) == 0:
            return
        T_c_w = np.stack([np.linalg.inv(np.asarray(T_w_b) @ spec.T_b_c) for spec in rig.cameras])
        T = wp.array(matrix_to_transform7(T_c_w).astype(np.float32), dtype=wp.transform, device=self.device)
        r = wp.array(np.ascontiguousarray(ratio, dtype=np.float32), dtype=float, device=self.device)
        g = self.gaussians
        wp.launch(follow_depth_kernel, dim=len(self), inputs=[g.means, g.log_scales, self.anchors_device(), int(keyframe), T, cameras, r], device=self.device)

    def follow_keyframes(self, old_T_w_b: np.ndarray, new_T_w_b: np.ndarray, scale: float = 1.0) -> None:
        """Move every keyframe's Gaussians from its old to its new rig pose."""
        for k, (A, B) in enumerate(zip(old_T_w_b, new_T_w_b)):
            if not np.allclose(A, B, atol=1e-9):
                self.move_anchored(k, B @ np.linalg.inv(A), scale)


FILL_MIN_SAMPLES = 16  # measured pixels a block needs before its plane is fitted


def fill_depth(depth: np.ndarray) -> np.ndarray:
    """``depth`` [H,W] (m, 0 = none) with its holes filled from their neighbourhood: each
    hole takes the plane (inverse depth affine in the pixel coordinates: exact for a plane
    seen by a pinhole camera, locally so under distortion) fitted to the valid pixels of the
    smallest 2^l block around it that holds at least ``FILL_MIN_SAMPLES`` of them spread over
    two dimensions, else their mean inverse depth (a push-pull pyramid of the fit's moments).
    A road or floor that nothing measured near the rig continues the slope it has where it
    was measured, instead of taking the far depth above it; the plane's value stays within
    3x of the block's mean inverse depth. All zeros stay zeros."""
    import cv2

    d = np.asarray(depth, np.float32)
    valid = d > 0
    if valid.all() or not valid.any():
        return d
    h, w = d.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    u, v = (u - w / 2) / max(h, w), (v - h / 2) / max(h, w)  # centred, unit scale: a well-conditioned fit
    s = np.where(valid, 1.0 / np.maximum(d, 1e-6), 0.0)
    wt = valid.astype(np.float64)
    # moments: 1, u, v, uu, uv, vv, s, su, sv (each times the valid weight)
    moments = np.stack([wt, wt * u, wt * v, wt * u * u, wt * u * v, wt * v * v, wt * s, wt * s * u, wt * s * v])
    levels = [moments]
    while max(levels[-1].shape[1:]) > 1 and levels[-1][0].min() < FILL_MIN_SAMPLES:
        m = levels[-1]
        h2, w2 = (m.shape[1] + 1) // 2, (m.shape[2] + 1) // 2
        m = np.pad(m, ((0, 0), (0, 2 * h2 - m.shape[1]), (0, 2 * w2 - m.shape[2])))
        levels.append(m.reshape(9, h2, 2, w2, 2).sum((2, 4)))

    def plane(m, level: int, top: bool):
        """Per block of ``2^level`` px: (a, b, c, mean) of s = a u + b v + c, and whether the
        block is usable (enough samples; at the top any)."""
        n = m[0]
        safe = np.maximum(n, 1e-12)
        mean = m[6] / safe
        mu, mv = m[1] / safe, m[2] / safe
        cuu, cuv, cvv = m[3] / safe - mu * mu, m[4] / safe - mu * mv, m[5] / safe - mv * mv
        csu, csv = m[7] / safe - mean * mu, m[8] / safe - mean * mv
        det = cuu * cvv - cuv * cuv
        full = (2**level / max(h, w)) ** 2 / 12  # the variance of a whole block's coordinates
        spread = det > (0.1 * full) ** 2  # samples spread over two dimensions, not a line
        enough = n >= FILL_MIN_SAMPLES
        fit = enough & spread
        sd = np.where(fit, det, 1.0)
        a = np.where(fit, (csu * cvv - csv * cuv) / sd, 0.0)
        b = np.where(fit, (csv * cuu - csu * cuv) / sd, 0.0)
        c = mean - a * mu - b * mv
        usable = enough | (top & (n > 0))
        return np.stack([a, b, c, mean]), usable

    def upsample(coef, shape):
        return np.stack([cv2.resize(x, (2 * coef.shape[2], 2 * coef.shape[1]), interpolation=cv2.INTER_NEAREST)[: shape[0], : shape[1]] for x in coef])

    coef, _ = plane(levels[-1], len(levels) - 1, True)
    for level in range(len(levels) - 2, 0, -1):
        here, usable = plane(levels[level], level, False)
        coef = np.where(usable[None], here, upsample(coef, levels[level].shape[1:]))
    if len(levels) > 1:
        coef = upsample(coef, (h, w))
    a, b, c, mean = coef
    inv = np.clip(a * u + b * v + c, mean / 3, mean * 3)
    return np.where(valid, d, 1.0 / np.maximum(inv, 1e-6)).astype(np.float32)
