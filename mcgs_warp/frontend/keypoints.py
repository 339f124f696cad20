"""Keypoints: SIFT features of each view, descriptor matching, and their depth from what
the rig measures (sensor depth, or triangulation between the rig's overlapping cameras).

The sparse part of the front end (ORB-SLAM / classical stereo VO style). Dense DIS flow
matches almost every pixel but fails where the motion is large or the texture poor; a few
hundred distinctive keypoints with a descriptor survive both, and anchor each new frame's
pose (:mod:`.pnp`, :mod:`.keypoint_tracker`).

Conventions: pixels at the processing resolution (OpenCV centres); bearings are unit
vectors in the camera frame (any camera model: from :func:`~mcgs_warp.ba.edges.unproject_pixels`);
a keypoint's camera-frame point is its unit-depth ray times its depth (distance along the
optical axis, ray length for equirectangular cameras), NaN where unknown.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..rig import Rig


@dataclass
class ViewKeypoints:
    """Keypoints of one camera image."""

    uv: np.ndarray  # [M,2] float64 px
    rays: np.ndarray  # [M,3] float64 unit-depth rays (point = ray x depth), camera frame
    bearings: np.ndarray  # [M,3] float64 unit vectors, camera frame
    desc: np.ndarray  # [M,128] SIFT descriptors: uint8 (OpenCV's float32 values are whole numbers 0-255; a quarter of the memory a kept keyframe holds), float32 for matching (:func:`descriptors`)
    points: np.ndarray  # [M,3] float64 camera-frame points (m), NaN where the depth is unknown
    #: stereo matches with the rig's other cameras at the same time: camera -> (indices here, indices there)
    partners: dict = field(default_factory=dict)
    sensed: np.ndarray | None = None  # [M] bool: the depth is exact sensor depth (bundle adjustment holds it; stereo depth it refines)

    def __len__(self) -> int:
        return len(self.uv)

    @property
    def has_depth(self) -> np.ndarray:
        return np.isfinite(self.points[:, 0])


def to_grey8(image: np.ndarray) -> np.ndarray:
    """[H,W,3] float RGB in [0,1] (or [H,W]) -> [H,W] uint8 grey."""
    g = image if image.ndim == 2 else image @ np.array([0.299, 0.587, 0.114], dtype=image.dtype)
    return np.clip(g * 255.0 + 0.5, 0, 255).astype(np.uint8)


def compact_descriptors(desc: np.ndarray | None) -> np.ndarray:
    """SIFT descriptors [M,128] as a view keeps them: uint8 where every value is a whole number
    in 0-255 (OpenCV's SIFT gives such float32s), else float32."""
    if desc is None:
        return np.zeros((0, 128), np.uint8)
    desc = np.asarray(desc)
    if desc.dtype == np.uint8:
        return desc
    n = np.clip(desc, 0, 255).astype(np.uint8)
    return n if np.array_equal(n, desc) else desc.astype(np.float32)


def descriptors(desc: np.ndarray) -> np.ndarray:
    """Kept descriptors (:func:`compact_descriptors`) as the float32 the matchers take."""
    return np.asarray(desc, np.float32)


def mutual_matches(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """Pairs [P,2] (index in a, index in b) whose nearest neighbours agree both ways and pass
    Lowe's ratio test (nearest < ``ratio`` x second nearest) in both directions."""
    import cv2

    desc_a, desc_b = descriptors(desc_a), descriptors(desc_b)
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(cv2.NORM_L2)

    def best(x, y):
        knn = bf.knnMatch(x, y, k=2)
        idx = np.array([m[0].trainIdx for m in knn], np.int64)
        ok = np.array([len(m) == 2 and m[0].distance < ratio * m[1].distance for m in knn], bool)
        return idx, ok

    ab, ok_ab = best(desc_a, desc_b)
    ba, ok_ba = best(desc_b, desc_a)
    a = np.nonzero(ok_ab & ok_ba[ab] & (ba[ab] == np.arange(len(desc_a))))[0]
    return np.stack([a, ab[a]], 1)


def masked_matches(desc_a: np.ndarray, desc_b: np.ndarray, allowed: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """Pairs [P,2] (index in a, index in b) matched among ``allowed`` [Ma,Mb] candidates only
    (an epipolar band, a search window around a predicted position): the best descriptor
    there, mutual, and below ``ratio`` times the second best there."""
    if not allowed.any():
        return np.zeros((0, 2), np.int64)
    desc_a, desc_b = descriptors(desc_a), descriptors(desc_b)
    d2 = (desc_a**2).sum(1)[:, None] + (desc_b**2).sum(1)[None] - 2.0 * desc_a @ desc_b.T
    d2 = np.where(allowed, np.maximum(d2, 0.0), np.inf)
    ia = np.arange(len(desc_a))
    ib = np.argmin(d2, 1)
    best = d2[ia, ib]
    d2[ia, ib] = np.inf
    second = d2.min(1)
    d2[ia, ib] = best
    ok = np.isfinite(best) & (np.sqrt(best) < ratio * np.sqrt(second)) & (np.argmin(d2, 0)[ib] == ia)
    return np.stack([ia[ok], ib[ok]], 1)


def triangulate(T_a_b: np.ndarray, bear_a: np.ndarray, bear_b: np.ndarray):
    """Midpoint triangulation of rays ``bear_a`` [P,3] (frame a) and ``bear_b`` [P,3] (frame b),
    ``T_a_b`` [4,4] or one per pair [P,4,4]: points [P,3] in frame a, and the ray ranges [P]
    along a and along b (negative: behind)."""
    R, t = T_a_b[..., :3, :3], T_a_b[..., :3, 3]
    batch = T_a_b.ndim == 3
    db = np.einsum("pij,pj->pi", R, bear_b) if batch else bear_b @ R.T  # b's rays in frame a
    # minimise |s da - (t + r db)|: 2x2 normal equations per pair
    aa = np.einsum("ij,ij->i", bear_a, bear_a)
    bb = np.einsum("ij,ij->i", db, db)
    ab = np.einsum("ij,ij->i", bear_a, db)
    at = np.einsum("pi,pi->p", bear_a, t) if batch else bear_a @ t
    bt = np.einsum("pi,pi->p", db, t) if batch else db @ t
    det = aa * bb - ab * ab
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (at * bb - ab * bt) / det
        r = (ab * at - aa * bt) / det
    X = 0.5 * (s[:, None] * bear_a + t + r[:, None] * db)
    return X, s, r


class KeypointDetector:
    """SIFT keypoints of every view of a rig frame, with depth from sensor depth where the
    frame has it, else from the rig's overlapping camera pairs (``pairs``: (a, b) camera
    indices), matched both ways, checked against the epipolar geometry and triangulated
    where the parallax measures depth (nearer than ``max_baselines`` baselines)."""

    def __init__(self, rig: Rig, pairs=(), features: int = 1000, ratio: float = 0.8, epipolar_rad: float = 0.003, max_baselines: float = 40.0):
        from ..ba.edges import unproject_pixels

        self.rig, self.features, self.ratio = rig, features, ratio
        self.pairs = sorted({(min(a, b), max(a, b)) for a, b in pairs})
        self.epipolar_rad, self.max_baselines = epipolar_rad, max_baselines
        self._cams = [c.warp_camera() for c in rig.cameras]
        self._unproject = unproject_pixels

    def _refined(self, a: int, b: int, ia, ib, views) -> np.ndarray:
        """Bearings in view b of keypoints ``ia`` of view a, their match ``ib`` refined to a
        sub-pixel position by pyramidal Lucas-Kanade of a's patch (two independently detected
        keypoints each carry ~0.3 px of noise, which is 3 % of depth at 10 px of disparity)."""
        import cv2

        bb = views[b].bearings[ib]
        if not len(ia):
            return bb
        p0 = views[a].uv[ia].astype(np.float32).reshape(-1, 1, 2)
        p1 = views[b].uv[ib].astype(np.float32).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
        p1r, st, _err = cv2.calcOpticalFlowPyrLK(self._grey[a], self._grey[b], p0, p1.copy(), winSize=(11, 11), maxLevel=1, criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        p1r = p1r.reshape(-1, 2).astype(np.float64)
        moved = np.linalg.norm(p1r - views[b].uv[ib], axis=1)
        good = (st.ravel() == 1) & (moved < 1.5)
        if good.any():
            rays = self._unproject(self._cams[b], p1r[good])
            bb = bb.copy()
            bb[good] = rays / np.linalg.norm(rays, axis=1, keepdims=True)
            vb = views[b]  # the refined position is the keypoint's (it is where a's patch is) unless its point is already on its old ray (sensor depth)
            move = ~vb.has_depth[ib[good]]
            idx = ib[good][move]
            vb.uv[idx], vb.rays[idx], vb.bearings[idx] = p1r[good][move], rays[move], bb[good][move]
        return bb

    def detect(self, images, depths=None) -> list[ViewKeypoints]:
        """Keypoints [C] of one rig frame (``images`` [C] of [H,W,3] in [0,1]; ``depths`` [C]
        of [H,W] m or None)."""
        import cv2

        sift = cv2.SIFT_create(nfeatures=self.features, contrastThreshold=0.02)
        views = []
        self._grey = [to_grey8(img) for img in images]
        for c, img in enumerate(self._grey):
            kps, desc = sift.detectAndCompute(img, None)
            uv = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
            desc = compact_descriptors(desc)
            rays = self._unproject(self._cams[c], uv) if len(uv) else np.zeros((0, 3))
            pts = np.full((len(uv), 3), np.nan)
            if depths is not None and depths[c] is not None and len(uv):
                d = depths[c]
                ui = np.clip(np.rint(uv[:, 0]).astype(int), 0, d.shape[1] - 1)
                vi = np.clip(np.rint(uv[:, 1]).astype(int), 0, d.shape[0] - 1)
                z = d[vi, ui].astype(np.float64)
                ok = z > 0
                pts[ok] = rays[ok] * z[ok, None]
            norm = np.linalg.norm(rays, axis=1, keepdims=True)
            views.append(ViewKeypoints(uv, rays, rays / np.maximum(norm, 1e-12), desc, pts, sensed=np.isfinite(pts[:, 0])))
        for a, b in self.pairs:
            self._stereo(views, a, b)
        return views

    def _stereo(self, views, a: int, b: int) -> None:
        """Depth of pair (a, b)'s common keypoints that have none yet (both views). Matching
        is restricted to the epipolar band (``epipolar_rad``), as stereo matching along rows
        is: the best descriptor there, mutual and distinct from the band's second best."""
        va, vb = views[a], views[b]
        if len(va) < 2 or len(vb) < 2:
            return
        T_a_b = np.linalg.inv(self.rig.cameras[a].T_b_c) @ self.rig.cameras[b].T_b_c
        baseline = float(np.linalg.norm(T_a_b[:3, 3]))
        if baseline <= 0:
            return
        n = np.cross(va.bearings, T_a_b[:3, 3] / baseline)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        band = np.abs(n @ (vb.bearings @ T_a_b[:3, :3].T).T) < self.epipolar_rad  # [Ma,Mb]
        m = masked_matches(va.desc, vb.desc, band, self.ratio)
        ia, ib = m[:, 0], m[:, 1]
        ba, bb = va.bearings[ia], self._refined(a, b, ia, ib, views)
        X, s, r = triangulate(T_a_b, ba, bb)
        rng = np.linalg.norm(X, axis=1)
        ok = (s > 0) & (r > 0) & (rng < self.max_baselines * baseline) & np.isfinite(rng)
        # each view keeps the point on its own ray, at the triangulated range
        for view, idx, P in ((va, ia, s[:, None] * ba), (vb, ib, r[:, None] * bb)):
            free = ok & ~view.has_depth[idx]
            view.points[idx[free]] = P[free]
        va.partners[b] = (ia[ok], ib[ok])
