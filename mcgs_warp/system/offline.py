"""The offline stage's photo-consistency pass (paper Fig. 3, bottom): after global MCBA the
estimated depth targets are re-checked against the images with the solved poses
(:func:`photo_consistent_targets`). :meth:`~mcgs_warp.system.slam.SLAM.refine` wires the
offline stage: the tracker's global MCBA, this pass, joint refinement.
"""

from __future__ import annotations

import numpy as np


def source_scores(rays: np.ndarray, depth: np.ndarray, cams, T_src_ref: np.ndarray, stride: int = 8, theta0: float = 5.0, sigma_below: float = 1.0, sigma_above: float = 10.0) -> np.ndarray:
    """How well each source view [S] can judge a reference view's depth, MVSNet's view score:
    over the reference's points (``rays`` [H,W,3] unit-depth times ``depth`` [H,W] m, every
    ``stride`` px) that land inside source ``s`` (Warp camera ``cams[s]``, ``T_src_ref[s]``),
    the sum of ``exp(-(theta - theta0)^2 / (2 sigma^2))`` over their triangulation angle
    ``theta`` (degrees, at the point between the two camera centres; ``sigma_below`` under
    ``theta0``, ``sigma_above`` over it). A view without parallax or overlap scores ~0; a
    view that sees much of the reference from about ``theta0`` away scores highest."""
    from ..ba.edges import project_points

    z = np.asarray(depth, np.float64)[::stride, ::stride]
    X = np.asarray(rays, np.float64)[::stride, ::stride][z > 0] * z[z > 0][:, None]
    scores = np.zeros(len(T_src_ref))
    if not len(X):
        return scores
    to_ref = X / np.linalg.norm(X, axis=1, keepdims=True)
    for s, (cam, T) in enumerate(zip(cams, T_src_ref)):
        R, t = T[:3, :3], T[:3, 3]
        uv, ok, _ = project_points(cam, X @ R.T + t)
        inside = ok & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
        d = X[inside] + R.T @ t  # from the source's centre (-R^T t in the reference frame) to the point
        cos = np.sum(to_ref[inside] * d, axis=1) / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        theta = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        sigma = np.where(theta <= theta0, sigma_below, sigma_above)
        scores[s] = np.exp(-((theta - theta0) ** 2) / (2 * sigma**2)).sum()
    return scores


def photo_consistent_targets(buf, stereo_pairs, keyframes, radius: int, min_views: int = 0, progress=None, sources: int = 0) -> dict:
    """Sharpen estimated mapping targets with the solved poses: one PatchMatch-style pass
    (:func:`~mcgs_warp.kernels.propagation.propagate_depth`) per view against the same camera
    up to ``radius`` keyframes either side and the rig's overlapping cameras at the same
    time. MCBA's depth lives on a grid of 8 px cells and is upsampled, so depth edges
    spread over a cell and plain surfaces carry the grid's error; each pixel now takes
    the nearby depth (or a 2-5 % change of its own) that its 9x9 window matches best
    (at depth edges with colour-adaptive window weights, against foreground fattening).
    With ``sources`` > 0 each view is matched against only that many of those views, the
    best by :func:`source_scores` (as MVSNet, COLMAP and ACMM select views): the pass's
    cost grows with the views it matches.
    Then, with ``min_views`` > 0, a target pixel is kept only where at least that many of
    those views' new targets put the point within 5 % of it
    (:func:`~mcgs_warp.kernels.propagation.consistent_depth`); the rest get no depth target.
    Reads the buffer's images, poses and targets of ``keyframes`` (mapped ones only); returns
    the new targets (keyframe -> per camera [H,W] m) for the mapper to take."""
    from ..frontend.stereo import grey
    from ..kernels.propagation import consistent_depth, propagate_depth

    rig = buf.rig
    poses, rays = buf.get_poses(), buf.full_rays
    T_w_c = {(k, c): poses[k] @ spec.T_b_c for k in range(len(buf)) for c, spec in enumerate(rig.cameras)}
    cams = [spec.warp_camera() for spec in rig.cameras]
    greys: dict = {}
    rays_np = [rays[c].numpy() for c in range(len(rig))] if sources > 0 else None

    def grey_of(k, c):
        if (k, c) not in greys:
            greys[(k, c)] = grey(buf.image(k, c), 1)
        return greys[(k, c)]

    todo = sorted(k for k in keyframes if k in buf.targets)
    new: dict = {}

    def views_of(k, c, mapped: bool = False):
        """The views (keyframe, camera) that judge view (k, c), and T_src_ref [S,4,4]."""
        views = [(k2, c) for k2 in range(max(0, k - radius), min(len(buf), k + radius + 1)) if k2 != k]
        views += [(k, b) for a, b in stereo_pairs if a == c]
        views = [v for v in views if v[0] in buf.targets] if mapped else views
        return views, np.stack([np.linalg.inv(T_w_c[v]) @ T_w_c[(k, c)] for v in views]) if views else np.zeros((0, 4, 4))

    for n, k in enumerate(todo):
        for key in [key for key in greys if key[0] < k - radius]:
            del greys[key]  # keyframes in order: hold only the views a later one still uses
        targets = []
        for c in range(len(rig)):
            views, T_src_ref = views_of(k, c)
            depth = np.asarray(buf.targets[k][c], np.float32)
            if 0 < sources < len(views):
                score = source_scores(rays_np[c][: depth.shape[0], : depth.shape[1]], depth, [cams[v[1]] for v in views], T_src_ref)
                best = sorted(np.argsort(-score, kind="stable")[:sources])
                views, T_src_ref = [views[i] for i in best], T_src_ref[best]
            targets.append(propagate_depth(grey_of(k, c), rays[c], depth, [grey_of(*v) for v in views], [cams[v[1]] for v in views], T_src_ref, ref_colour=buf.image(k, c), device=buf.device))
        new[k] = targets
        if progress is not None:
            progress("photo depth", n + 1, len(todo))
    if min_views <= 0:
        return new
    kept = {}  # judged against the other views' unfiltered targets, then replaced together
    for k in todo:
        kept[k] = []
        for c in range(len(rig)):
            views, T_src_ref = views_of(k, c, mapped=True)
            kept[k].append(consistent_depth(rays[c], new[k][c], [rays[v[1]] for v in views], [new[v[0]][v[1]] for v in views], [cams[v[1]] for v in views], T_src_ref, min_views=min_views, device=buf.device))
    return kept

