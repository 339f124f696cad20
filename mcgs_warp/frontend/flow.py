"""Dense correspondences for MCBA edges, behind a small interface.

A :class:`FlowProvider` turns the edges of the keyframe buffer into targets
``p~_ij`` (the pixel of view (j, cj) matching each reduced-grid pixel of view
(i, ci), in reduced-grid coordinates) and confidences ``w_ij`` in [0, 1]. The
paper uses a learned recurrent flow network (RFT); here:

* :class:`DISFlow` — OpenCV's DIS optical flow, forward and backward, with the
  forward-backward consistency as confidence (0 on flat patches, :func:`textured`); any
  learned flow can replace it by implementing ``flow(image_a, image_b)``.
* :class:`GroundTruthFlow` — exact correspondences from depth and poses (synthetic
  data, tests), with occlusions removed by a depth test.
"""

from __future__ import annotations

import copy
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..ba.edges import project_points
from ..buffer import KeyframeBuffer, grid_pixels
from ..kernels.launch import cpu_workers


class FlowProvider:
    def correspondences(self, buffer: KeyframeBuffer, edges: np.ndarray):
        """``targets`` [E,h,w,2] (reduced-grid pixels of view (j, cj)) and ``weights`` [E,h,w]."""
        raise NotImplementedError


class NoCorrespondences(FlowProvider):
    """Every edge without a correspondence (``--correspondences none``: the sparse core of
    the system, keypoint tracks alone in MCBA, as an ablation)."""

    def correspondences(self, buffer: KeyframeBuffer, edges: np.ndarray):
        E = len(edges)
        return np.zeros((E, buffer.h, buffer.w, 2), np.float32), np.zeros((E, buffer.h, buffer.w), np.float32)


#: grey-level std (images in [0, 1]) of a 7x7 window below which a pixel's match carries no
#: information: a flat patch (overexposed sky, a blank wall) matches itself anywhere nearby,
#: and both the forward-backward check and the patch SAD pass it. Such grid pixels get weight 0
#: (KITTI: the sky, 10-16 % of the grid; the built-in sequence: 1.4-2.4 %).
FLAT_STD = 0.005


def textured(image: np.ndarray, uv: np.ndarray, radius: int = 3) -> np.ndarray:
    """bool [h,w]: whether the (2 radius + 1)^2 grey window of ``image`` [H,W,3] around each
    pixel ``uv`` [h,w,2] (rounded, clipped to the image) has a std of at least :data:`FLAT_STD`."""
    import cv2

    g = cv2.cvtColor(np.asarray(image, np.float32), cv2.COLOR_RGB2GRAY)
    k = (2 * radius + 1, 2 * radius + 1)
    m, m2 = cv2.boxFilter(g, -1, k), cv2.boxFilter(g * g, -1, k)
    std = np.sqrt(np.maximum(m2 - m * m, 0.0))
    u = np.clip(np.rint(np.nan_to_num(uv[..., 0])), 0, g.shape[1] - 1).astype(int)
    v = np.clip(np.rint(np.nan_to_num(uv[..., 1])), 0, g.shape[0] - 1).astype(int)
    return std[v, u] >= FLAT_STD


def to_reduced(uv: np.ndarray, stride: int) -> np.ndarray:
    """Full-resolution pixels -> reduced-grid pixels (grid pixel u' is ``stride u' + stride // 2``)."""
    return (uv - stride // 2) / stride


def from_reduced(uv: np.ndarray, stride: int) -> np.ndarray:
    """Reduced-grid pixels -> full-resolution pixels (the inverse of :func:`to_reduced`)."""
    return uv * stride + stride // 2


@dataclass
class FlowConfig:
    """The tracker's DIS correspondences (run configuration ``tracking.flow``)."""

    finest_scale: int = 0  # pyramid level DIS stops at (0: full resolution) where the correspondences measure depth (RGB only, seed 1: depth L1 0.206 -> 0.137 m at 0 with 4 px patches against the preset)
    patch_size: int = 4  # px
    smoothness: float = 5.0  # weight of flow smoothness in DIS's variational refinement (fewer gross errors on wide edges than the preset's 20)
    sigma: float = 1.0  # full-resolution px: the forward-backward error at which a match's confidence is exp(-1)
    settled_px: float = 0.25  # guided DIS: an edge whose guided flow moved less than this (full-resolution px, median) since its last match ...
    settled_outliers: float = 0.05  # ... with fewer than this share of its pixels moved more than 1 px is not matched again (GuidedDIS.settled)
    photo_sigma: float = 0.02  # grey levels in [0,1]: a guided match's confidence also falls as exp(-(SAD / photo_sigma)^2)
    min_confident: float = 0.25  # with exact sensor depth, a view whose guided matches are confident on fewer of its grid pixels than this share takes raw DIS instead (GuidedOrRaw)
    exact_depth_preset: bool = True  # with exact sensor depth the correspondences only constrain the poses: DIS's medium preset (half resolution, 8 px patches; 3.7x cheaper per call, the demo's SE(3) ATE 2.54 vs 2.31 mm) instead of the settings above


class DISFlow(FlowProvider):
    """OpenCV DIS flow with forward-backward consistency ``w = exp(-(e / sigma)^2)``
    (``e``: forward-backward error in full-resolution pixels). ``None`` keeps the preset's
    value of each of: ``finest_scale``, the pyramid level DIS stops at (0 = full resolution;
    the presets stop at 1, half resolution, and upsample: about 2.5x faster, but on the
    built-in sequence's temporal edges the guided matches' mean error is 0.36 instead of
    0.27 px, and plain DIS's 1.0 instead of 0.77 px); ``patch_size`` (px, preset 8) and
    ``smoothness``, the variational refinement's weight of flow smoothness (preset 20;
    the tracker takes :class:`FlowConfig`'s full resolution, 4 px and 5 wherever the matches
    measure depth, i.e. without exact sensor depth: fewer gross errors on wide edges)."""

    def __init__(self, preset: str = "medium", sigma: float = 1.0, finest_scale: int | None = None, patch_size: int | None = None, smoothness: float | None = None):
        self.settings = (preset, finest_scale, patch_size, smoothness)
        self.dis = self._new_dis()
        self.sigma = sigma

    def _new_dis(self):
        import cv2

        preset, finest_scale, patch_size, smoothness = self.settings
        presets = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST, "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
        dis = cv2.DISOpticalFlow_create(presets[preset])
        if finest_scale is not None:
            dis.setFinestScale(finest_scale)
        if patch_size is not None:
            dis.setPatchSize(patch_size)
        if smoothness is not None:
            dis.setVariationalRefinementAlpha(smoothness)
        return dis

    def twin(self) -> "DISFlow":
        """A shallow copy with an OpenCV DIS object of its own (one is not thread-safe):
        a subclass stays that subclass, with its other attributes shared."""
        other = copy.copy(self)
        other.dis = self._new_dis()
        return other

    @staticmethod
    def _grey(img):
        import cv2

        return cv2.cvtColor((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2GRAY)

    def flow(self, image_a: np.ndarray, image_b: np.ndarray):
        """Dense flow [H,W,2] from a to b (px) and its confidence [H,W] in [0,1]."""
        return self.flows(image_a, image_b, both=False)[0]

    def flows(self, image_a: np.ndarray, image_b: np.ndarray, both: bool = True):
        """Both directions from the same two DIS runs: ``((flow a->b [Ha,Wa,2], confidence
        [Ha,Wa]), (flow b->a [Hb,Wb,2], confidence [Hb,Wb]))``; the second equals
        ``flow(image_b, image_a)`` (``None`` unless ``both``)."""
        import cv2

        a, b = self._grey(image_a), self._grey(image_b)
        if a.shape != b.shape:  # different cameras: compare on a common canvas
            H, W = max(a.shape[0], b.shape[0]), max(a.shape[1], b.shape[1])
            a = cv2.copyMakeBorder(a, 0, H - a.shape[0], 0, W - a.shape[1], cv2.BORDER_REPLICATE)
            b = cv2.copyMakeBorder(b, 0, H - b.shape[0], 0, W - b.shape[1], cv2.BORDER_REPLICATE)
        fwd = self.dis.calc(a, b, None)
        bwd = self.dis.calc(b, a, None)
        H, W = a.shape
        v, u = np.mgrid[0:H, 0:W].astype(np.float32)

        def checked(f, g, shape):
            back = cv2.remap(g, u + f[..., 0], v + f[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1e4)
            err = np.linalg.norm(f + back, axis=-1)
            h0, w0 = shape[:2]
            return f[:h0, :w0], np.exp(-((err[:h0, :w0] / self.sigma) ** 2))

        return checked(fwd, bwd, image_a.shape), (checked(bwd, fwd, image_b.shape) if both else None)

    def correspondences(self, buffer: KeyframeBuffer, edges: np.ndarray):
        """Targets and weights of ``edges``; grid pixels flat at either end (:func:`textured`) get weight 0."""
        E = len(edges)
        targets = np.zeros((E, buffer.h, buffer.w, 2), np.float32)
        weights = np.zeros((E, buffer.h, buffer.w), np.float32)
        reverse: dict = {}  # edge -> its grid targets, from its reverse's two DIS runs
        wanted = {tuple(e) for e in edges[:, :4].tolist()}
        for e, (i, ci, j, cj) in enumerate(edges[:, :4].tolist()):
            if (i, ci, j, cj) in reverse:
                targets[e], weights[e] = reverse.pop((i, ci, j, cj))
                continue
            forward, back = self.flows(buffer.image(i, ci), buffer.image(j, cj))
            targets[e], weights[e] = grid_targets(buffer, ci, cj, *forward)
            if (j, cj, i, ci) in wanted:
                reverse[(j, cj, i, ci)] = grid_targets(buffer, cj, ci, *back)
        for e, (i, ci, j, cj) in enumerate(edges[:, :4].tolist()):  # texture at both ends: a flat target matches anything
            uv = grid_pixels(buffer.rig.cameras[ci], buffer.stride)
            h, w = uv.shape[:2]
            weights[e, :h, :w] *= textured(buffer.image(i, ci), uv) & textured(buffer.image(j, cj), from_reduced(targets[e, :h, :w], buffer.stride))
        return targets, weights


def grid_targets(buffer: KeyframeBuffer, ci: int, cj: int, flow: np.ndarray, conf: np.ndarray):
    """A dense flow [H,W,2] (px) of view ci towards view cj and its confidence [H,W],
    sampled at the reduced-grid pixels of ci: targets [h,w,2] in reduced-grid pixels of cj
    and weights [h,w] (0 where the target leaves view cj), padded to the buffer's grid."""
    s = buffer.stride
    uv = grid_pixels(buffer.rig.cameras[ci], s)
    ui, vi = uv[..., 0].astype(int), uv[..., 1].astype(int)
    h, w = uv.shape[:2]
    t = uv + flow[vi, ui]  # full-resolution pixel in view cj
    cam_j = buffer.rig.cameras[cj]
    inside = (t[..., 0] >= 0) & (t[..., 0] <= cam_j.width - 1) & (t[..., 1] >= 0) & (t[..., 1] <= cam_j.height - 1)
    targets = np.zeros((buffer.h, buffer.w, 2), np.float32)
    weights = np.zeros((buffer.h, buffer.w), np.float32)
    targets[:h, :w] = to_reduced(t, s)
    weights[:h, :w] = conf[vi, ui] * inside
    return targets, weights


def project_grid_depth(buffer: KeyframeBuffer, ci: int, z: np.ndarray, T_cj_ci: np.ndarray, cj: int, rays=None):
    """Full-resolution pixels [h*w,2] of view cj seen at the reduced-grid pixels of view ci
    with depth ``z`` [h,w] (m, 0 = none), and whether each lands inside view cj. ``rays``:
    the buffer's grid rays on the host ([C,h,w,3], ``buffer.rays.numpy()``), read once by
    callers that loop over edges."""
    h, w = z.shape
    rays = buffer.rays.numpy() if rays is None else rays
    X = rays[ci, :h, :w].astype(np.float64) * z[..., None]
    Xj = X.reshape(-1, 3) @ T_cj_ci[:3, :3].T + T_cj_ci[:3, 3]
    cam = buffer.rig.cameras[cj].warp_camera()
    p, ok, _ = project_points(cam, Xj)
    ok &= z.reshape(-1) > 0
    inside = ok & (p[:, 0] >= 0) & (p[:, 0] <= cam.width - 1) & (p[:, 1] >= 0) & (p[:, 1] <= cam.height - 1)
    return p, inside, Xj


class GroundTruthFlow(FlowProvider):
    """Exact correspondences from full-resolution depth maps and poses.

    ``depths[k][c]`` [H,W] (m, camera-model depth) and ``T_w_b`` [K,4,4] are the true
    values for the buffer's keyframes. A correspondence counts (weight 1) where the
    point lands inside view (j, cj) and that view's depth map sees the same surface
    (within ``rel_tol``), else weight 0."""

    def __init__(self, depths, T_w_b: np.ndarray, rel_tol: float = 0.02):
        self.depths = depths
        self.T_w_b = None if T_w_b is None else np.asarray(T_w_b, dtype=np.float64)
        self.rel_tol = rel_tol

    def depths_of(self, buffer: KeyframeBuffer, k: int) -> list:
        return self.depths[k]

    def pose_of(self, buffer: KeyframeBuffer, k: int) -> np.ndarray:
        return self.T_w_b[k]

    def correspondences(self, buffer: KeyframeBuffer, edges: np.ndarray):
        E, s = len(edges), buffer.stride
        targets = np.zeros((E, buffer.h, buffer.w, 2), np.float32)
        weights = np.zeros((E, buffer.h, buffer.w), np.float32)
        rays = buffer.rays.numpy()
        for e, (i, ci, j, cj) in enumerate(edges[:, :4]):
            spec_i = buffer.rig.cameras[ci]
            uv = grid_pixels(spec_i, s)
            h, w = uv.shape[:2]
            z = self.depths_of(buffer, i)[ci][uv[..., 1].astype(int), uv[..., 0].astype(int)].astype(np.float64)
            T = np.linalg.inv(self.pose_of(buffer, j) @ buffer.rig.cameras[cj].T_b_c) @ self.pose_of(buffer, i) @ spec_i.T_b_c
            p, inside, Xj = project_grid_depth(buffer, ci, z, T, cj, rays)
            pr = np.round(np.where(inside[:, None], p, 0)).astype(int)
            seen = self.depths_of(buffer, j)[cj][pr[:, 1], pr[:, 0]]
            pred = np.linalg.norm(Xj, axis=-1) if buffer.rig.cameras[cj].model == "equirectangular" else Xj[:, 2]  # the model's depth (DESIGN.md)
            visible = inside & (np.abs(seen - pred) <= self.rel_tol * pred)
            targets[e, :h, :w] = to_reduced(p, s).reshape(h, w, 2)
            weights[e, :h, :w] = visible.reshape(h, w)
        return targets, weights


class SequenceGroundTruthFlow(GroundTruthFlow):
    """:class:`GroundTruthFlow` for a sequence's keyframes, looked up by frame: the exact
    depth of ``sequence.gt_depths`` and the poses of ``sequence.groundtruth`` (the
    ``--correspondences ground-truth`` oracle; only relative poses enter, so the
    ground truth's world frame does not matter)."""

    def __init__(self, sequence, rel_tol: float = 0.02, max_dt: float = 0.02):
        from ..errors import InputError

        where = getattr(sequence, "root", None) or sequence.name or "the sequence"
        if sequence.groundtruth is None:
            raise InputError(where, None, "--correspondences ground-truth needs ground-truth poses (groundtruth.txt); this sequence has none")
        if sequence.gt_depths(0) is None:
            raise InputError(where, None, "--correspondences ground-truth needs exact depth (gt/cam<i>/depth, or exact cam<i>/depth); this sequence has none")
        super().__init__(None, None, rel_tol)
        self.seq, self.max_dt = sequence, max_dt
        self._depths: dict = {}

    def depths_of(self, buffer, k):
        f = buffer.frame_index[k]
        if f not in self._depths:
            self._depths[f] = self.seq.gt_depths(f)
        return self._depths[f]

    def pose_of(self, buffer, k):
        from ..errors import InputError

        gt = self.seq.groundtruth
        t = buffer.timestamps[k]
        n = int(np.argmin(np.abs(gt.timestamps - t)))
        if abs(gt.timestamps[n] - t) > self.max_dt:
            raise InputError("groundtruth.txt", None, f"no ground-truth pose within {self.max_dt} s of keyframe time {t:.6f} (needed by --correspondences ground-truth)")
        return gt.poses[n]


class StereoMatches(FlowProvider):
    """Cross-view correspondences from the rig's sweep stereo: the matched pixel of view
    (k, b) for each grid pixel of (k, a) is where the sweep's depth puts it (a 1-D search
    along the epipolar curve, left-right checked), weighted by the sweep's confidence.
    The sweep runs at reduced resolution with planes a pixel apart, and a grid pixel reads
    the depth of the sweep pixel it falls in; so each grid pixel's depth is then refined
    at full resolution at that very pixel (:func:`~mcgs_warp.kernels.refine.refine_points`,
    ``refine_px`` steps of epipolar motion, ``refine_count`` either way, a ZNCC window of
    ``(2 refine_radius + 1)^2`` pixels; count 0: off), and a
    grid pixel whose refinement runs to the end of that range gets no match. (On the
    built-in sequence this halves the matches' median depth error, 2.4-3.5 % to
    1.3-2.1 %.)"""

    def __init__(self, stereo, refine_px: float = 0.25, refine_count: int = 12, refine_radius: int = 4):
        self.stereo = stereo  # mcgs_warp.frontend.stereo.RigStereo
        self.refine_px, self.refine_count, self.refine_radius = refine_px, refine_count, refine_radius

    def correspondences(self, buffer: KeyframeBuffer, edges: np.ndarray):
        from ..kernels.refine import refine_points
        from .stereo import grey, upsample_nearest

        E, s = len(edges), buffer.stride
        targets = np.zeros((E, buffer.h, buffer.w, 2), np.float32)
        weights = np.zeros((E, buffer.h, buffer.w), np.float32)
        rig, rays = buffer.rig, buffer.rays.numpy()
        greys: dict = {}  # (keyframe, camera) -> full-resolution grey image, once per call
        for e, (i, ci, j, cj) in enumerate(edges[:, :4]):
            if i != j or (ci, cj) not in self.stereo.pairs:
                continue
            res = self.stereo.pair_sweeps(buffer.frame_index[i], buffer.keyframe_images(i))[(ci, cj)]
            spec = rig.cameras[ci]
            uv = grid_pixels(spec, s).astype(int)
            h, w = uv.shape[:2]
            sc = self.stereo.cfg.scale
            z = upsample_nearest(res.depth(), spec, sc)[uv[..., 1], uv[..., 0]].astype(np.float64)
            conf = upsample_nearest(res.confidence.numpy(), spec, sc)[uv[..., 1], uv[..., 0]]
            T = np.linalg.inv(rig.cameras[cj].T_b_c) @ spec.T_b_c
            if self.refine_count > 0:
                has = (conf > 0) & (z > 0)
                for c in (ci, cj):
                    if (i, c) not in greys:
                        greys[(i, c)] = grey(buffer.image(i, c), 1)
                rho, _ = refine_points(greys[(i, ci)], buffer.full_rays[int(ci)], greys[(i, cj)], rig.cameras[cj].warp_camera(), T, uv[has], 1.0 / z[has], self.refine_px, self.refine_count, self.refine_radius, self.stereo.cfg.min_std, buffer.device)
                z[has] = np.where(rho > 0, 1.0 / np.maximum(rho, 1e-12), 0.0)
                conf = np.where(z > 0, conf, 0.0)
            p, inside, _ = project_grid_depth(buffer, ci, z, T, cj, rays)
            targets[e, :h, :w] = to_reduced(p, s).reshape(h, w, 2)
            weights[e, :h, :w] = (conf.reshape(-1) * inside).reshape(h, w)
        return targets, weights


class GuidedOrRaw(FlowProvider):
    """New edges matched around the predicted flow (``guided``), except where the prediction
    is too poor to guide (a bad constant-velocity start: too little of view i lands in view j
    with a confident match, judged on the geometric confidence alone): those edges are matched
    by plain DIS (``raw``) instead. Only the guided edges get the photometric factor."""

    def __init__(self, guided: "GuidedDIS", raw: DISFlow, min_confident: float = 0.25):
        self.guided, self.raw = guided, raw
        self.min_confident = min_confident  # fraction of the view's grid pixels

    def correspondences(self, buffer: KeyframeBuffer, edges: np.ndarray):
        targets, weights = self.guided.correspondences(buffer, edges, photometric=False)
        s = buffer.stride
        area = np.array([(buffer.rig.cameras[ci].height // s) * (buffer.rig.cameras[ci].width // s) for ci in edges[:, 1]], np.float64)
        poor = (weights > 0.5).sum(axis=(1, 2)) < self.min_confident * area
        if (~poor).any():
            targets[~poor], weights[~poor] = self.guided.photometric(buffer, edges[~poor], targets[~poor], weights[~poor])
        if poor.any():
            targets[poor], weights[poor] = self.raw.correspondences(buffer, edges[poor])
        return targets, weights


class GuidedDIS(FlowProvider):
    """Correspondences that follow the geometry (the role of the paper's recurrent flow
    update): each edge's flow is predicted from the current depth of view (i, ci) and the
    current poses, view (j, cj) is warped into view i by that prediction, and DIS finds
    only the residual ``r``; the target is the prediction at ``p + r``. Wide baselines,
    rotations and different camera models reduce to a small residual. Confidence: the
    residual's forward-backward consistency times ``exp(-(SAD / photo_sigma)^2)``, the
    7x7 grey-level patch difference at the match, mean removed
    (:func:`~mcgs_warp.kernels.refine.patch_sad`), zero where the
    prediction leaves view j and on flat patches (:func:`textured`). The photometric factor catches what the consistency check
    cannot: where DIS leaves a wrong prediction in place, both directions agree on it (RGB
    only, built-in sequence: confident temporal matches more than 4 px off 4.8 % -> 0.8 %,
    mean error 1.30 -> 0.46 px, 36 % fewer confident matches)."""

    def __init__(self, dis: DISFlow, settled_px: float = 0.25, settled_outliers: float = 0.05, photo_sigma: float = 0.02):
        if not photo_sigma > 0:
            raise ValueError(f"GuidedDIS: photo_sigma must be > 0 (np.inf: no photometric factor), got {photo_sigma}")
        self.dis = dis
        self.photo_sigma = photo_sigma  # grey levels in [0, 1]
        self.settled_px = settled_px  # full-resolution px (see settled)
        self.settled_outliers = settled_outliers
        self._twins: list[DISFlow] = []  # one more DIS per extra thread (correspondences)

    def settled(self, buffer: KeyframeBuffer, edges: np.ndarray, targets: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """bool [E]: edges whose current geometry already predicts their stored matches
        (``targets`` [E,h,w,2], ``weights`` [E,h,w]): over confident grid pixels (weight >
        0.5) the median distance is below ``settled_px`` and at most ``settled_outliers`` of
        them are more than 1 px off. Re-matching such an edge changes almost nothing (on the
        built-in sequence: median 0.05 px), so :meth:`FactorGraph.refresh` skips it."""
        s, rig, poses, disp, rays = buffer.stride, buffer.rig, buffer.get_poses(), buffer.disp.numpy(), buffer.rays.numpy()
        out = np.zeros(len(edges), bool)
        for e, (i, ci, j, cj) in enumerate(edges[:, :4].tolist()):
            spec_i, spec_j = rig.cameras[ci], rig.cameras[cj]
            hr, wr = spec_i.height // s, spec_i.width // s
            T = np.linalg.inv(poses[j] @ spec_j.T_b_c) @ poses[i] @ spec_i.T_b_c
            d = disp[i, ci, :hr, :wr]
            pred, inside, _ = project_grid_depth(buffer, ci, np.where(d > 0, 1.0 / np.maximum(d, 1e-12), 0.0), T, cj, rays)
            ok = (weights[e, :hr, :wr] > 0.5) & inside.reshape(hr, wr)
            if ok.sum() < 16:
                continue
            err = np.linalg.norm(pred.reshape(hr, wr, 2) - from_reduced(targets[e, :hr, :wr], s), axis=-1)[ok]
            out[e] = np.median(err) < self.settled_px and (err > 1.0).mean() <= self.settled_outliers
        return out

    def correspondences(self, buffer: KeyframeBuffer, edges: np.ndarray, photometric: bool = True):
        """Targets and weights of ``edges``; ``photometric=False`` leaves out the photometric
        factor (:meth:`photometric`): the geometric decisions built on this provider (is the
        prediction good enough to guide, is a loop confirmed) judge the geometry alone."""
        E = len(edges)
        targets = np.zeros((E, buffer.h, buffer.w, 2), np.float32)
        weights = np.zeros((E, buffer.h, buffer.w), np.float32)
        poses, disp = buffer.get_poses(), buffer.disp.numpy()

        def match(worker: int) -> None:
            dis = self.dis if worker == 0 else self._twins[worker - 1]
            for e in range(worker, E, workers):
                self._match(buffer, edges[e], poses, disp, dis, targets[e], weights[e])

        # CPU only: Warp's CUDA allocations from several threads are not safe (NVIDIA/warp#1491);
        # and only for a flow that can make per-thread copies of itself (DISFlow.twin)
        threaded = not buffer.device.is_cuda and hasattr(self.dis, "twin")
        workers = max(1, min(cpu_workers(), E)) if threaded else 1
        while len(self._twins) < workers - 1:
            self._twins.append(self.dis.twin())
        if workers == 1:
            match(0)
        else:
            # Edges are independent: threads take every workers-th edge, each with its own DIS,
            # OpenCV single-threaded meanwhile (DIS alone keeps only ~1.8 of 2 cores busy,
            # and the reprojection and remaps around it one). Same result as serial.
            import cv2
            import warp as wp

            from ..kernels import refine

            wp.load_module(refine, device=buffer.device)  # here, not raced by the threads
            buffer.full_rays  # made on first use: here too
            threads = cv2.getNumThreads()
            cv2.setNumThreads(1)
            try:
                with ThreadPoolExecutor(workers) as pool:
                    list(pool.map(match, range(workers)))
            finally:
                cv2.setNumThreads(threads)
        return self.photometric(buffer, edges, targets, weights) if photometric else (targets, weights)

    def _match(self, buffer: KeyframeBuffer, edge, poses: np.ndarray, disp: np.ndarray, dis: DISFlow, target: np.ndarray, weight: np.ndarray) -> None:
        """One edge ``(i, ci, j, cj, ...)``: writes its ``target`` [h,w,2] and ``weight`` [h,w]."""
        import cv2

        from ..kernels.refine import reproject
        from .depth import upsample_inverse_depth

        s, rig = buffer.stride, buffer.rig
        i, ci, j, cj = (int(v) for v in edge[:4])
        spec_i, spec_j = rig.cameras[ci], rig.cameras[cj]
        hr, wr = spec_i.height // s, spec_i.width // s
        full, _ = upsample_inverse_depth(disp[i, ci, :hr, :wr], spec_i, s)
        T = np.linalg.inv(poses[j] @ spec_j.T_b_c) @ poses[i] @ spec_i.T_b_c
        inv = np.where(full > 0, 1.0 / np.maximum(full, 1e-6), 0.0)
        pred = reproject(buffer.full_rays[ci][: spec_i.height, : spec_i.width], inv, T, spec_j.warp_camera(), buffer.device)  # NaN where unknown
        mx = np.nan_to_num(pred[..., 0], nan=-1e4).astype(np.float32)
        my = np.nan_to_num(pred[..., 1], nan=-1e4).astype(np.float32)
        warped = cv2.remap(buffer.image(j, cj), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        flow, conf = dis.flow(buffer.image(i, ci), warped)
        uv = grid_pixels(spec_i, s).astype(np.float32)
        ui, vi = uv[..., 0].astype(int), uv[..., 1].astype(int)
        q = uv + flow[vi, ui]
        # the prediction at p + r; NaN (unknown) neighbours make the sample NaN, never a blend
        t = np.stack([cv2.remap(np.ascontiguousarray(pred[..., a], dtype=np.float32), q[..., 0], q[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan) for a in (0, 1)], -1)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(t).all(-1) & (t[..., 0] >= 0) & (t[..., 0] <= spec_j.width - 1) & (t[..., 1] >= 0) & (t[..., 1] <= spec_j.height - 1)
        target[:hr, :wr] = np.where(ok[..., None], to_reduced(t.astype(np.float64), s), 0.0)
        weight[:hr, :wr] = conf[vi, ui] * ok * textured(buffer.image(i, ci), uv) * textured(buffer.image(j, cj), np.where(ok[..., None], t, 0.0))

    def photometric(self, buffer: KeyframeBuffer, edges: np.ndarray, targets: np.ndarray, weights: np.ndarray):
        """``weights`` times ``exp(-(SAD / photo_sigma)^2)`` at each matched grid pixel:
        the mean-removed 7x7 patch SAD of view (i, ci) at the grid pixel and view (j, cj) at
        its target, all edges in one launch (:func:`~mcgs_warp.kernels.refine.patch_sad`)."""
        import cv2

        from ..kernels.refine import patch_sad

        weights = weights.copy()
        if len(edges) == 0:
            return targets, weights
        s = buffer.stride
        views: list = []
        index: dict = {}  # (keyframe, camera) -> position in views, each grey image made once

        def view(k, c):
            if (k, c) not in index:
                index[(k, c)] = len(views)
                views.append(cv2.cvtColor(np.asarray(buffer.image(k, c), np.float32), cv2.COLOR_RGB2GRAY))
            return index[(k, c)]

        uv_a = np.full(weights.shape + (2,), -1e4, np.float32)  # outside a camera's grid: weight 0
        for e, ci in enumerate(edges[:, 1].tolist()):
            uv = grid_pixels(buffer.rig.cameras[ci], s)
            uv_a[e, : uv.shape[0], : uv.shape[1]] = uv
        uv_b = np.where((weights > 0)[..., None], from_reduced(targets, s), -1e4).astype(np.float32)
        va = [view(i, ci) for i, ci in edges[:, :2].tolist()]
        vb = [view(j, cj) for j, cj in edges[:, 2:4].tolist()]
        sad = patch_sad(views, va, vb, uv_a, uv_b, device=buffer.device)
        weights *= np.exp(-((sad / self.photo_sigma) ** 2))
        return targets, weights


