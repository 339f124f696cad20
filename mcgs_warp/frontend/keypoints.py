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


#: Stereo matching along the epipolar line (:func:`epipolar_zncc`), as classical stereo VO does on
#: rectified rows: an 11x11 patch, the match found less than SEARCH px from the descriptor's (the
#: parabola's neighbours inside the search), accepted at ZNCC >= ZNCC_MIN, on the line (the rows
#: beside score lower: within half a pixel of it) and unambiguous (no score along the line more than
#: 2 px from the peak, within UNIQUE px of the strip's centre, comes within ZNCC_MARGIN of it)
PATCH, SEARCH, UNIQUE, ZNCC_MIN, ZNCC_MARGIN = 5, 3, 12, 0.8, 0.05


def epipolar_directions(cam_a, cam_b, T_a_b: np.ndarray, bear_a: np.ndarray, bear_b: np.ndarray):
    """Where matches lie and which way their epipolar lines run: for bearings ``bear_a`` and
    ``bear_b`` [P,3] of matched keypoints (views a and b, ``T_a_b`` [4,4]), the pixel in b of
    the point on a's ray at the triangulated range (on b's epipolar line, any camera model),
    the lines' unit directions in a and in b at the match ([P,2] each, the image motion of one
    3D displacement within the epipolar plane, so both point the same way) and which are
    usable ([P] bool: in front of both cameras and projecting)."""
    from ..ba.edges import project_points

    R, t = T_a_b[:3, :3], T_a_b[:3, 3]
    _X, s, r = triangulate(T_a_b, bear_a, bear_b)
    rb = bear_b @ R.T  # b's bearings in frame a
    n = np.cross(bear_a, t)
    m = np.cross(n, bear_a / np.linalg.norm(bear_a, axis=1, keepdims=True) + rb / np.linalg.norm(rb, axis=1, keepdims=True))  # in the plane, across both rays
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-12)
    Xa = np.where((s > 0)[:, None], s[:, None], 1.0) * bear_a
    Xb = (Xa - t) @ R
    _, ok_a, Ja = project_points(cam_a, Xa, jacobian=True)
    q_b, ok_b, Jb = project_points(cam_b, Xb, jacobian=True)
    e_a, e_b = np.einsum("pij,pj->pi", Ja, m), np.einsum("pij,pj->pi", Jb, m @ R)
    na, nb = np.linalg.norm(e_a, axis=1), np.linalg.norm(e_b, axis=1)
    ok = ok_a & ok_b & (s > 0) & (r > 0) & (na > 1e-9) & (nb > 1e-9) & np.isfinite(s)
    return q_b, e_a / np.maximum(na, 1e-12)[:, None], e_b / np.maximum(nb, 1e-12)[:, None], ok


def _sample(grey: np.ndarray, centre: np.ndarray, e: np.ndarray, half_x: int, half_y: int) -> np.ndarray:
    """Patches [P, 2 half_y + 1, 2 half_x + 1] of ``grey`` (float32) around ``centre`` [P,2],
    their x axis along ``e`` [P,2] and y axis at +90 degrees of it, bilinear (edges replicated)."""
    import cv2

    xs = np.arange(-half_x, half_x + 1, dtype=np.float64)
    ys = np.arange(-half_y, half_y + 1, dtype=np.float64)
    nrm = np.stack([-e[:, 1], e[:, 0]], 1)
    g = centre[:, None, None, :] + xs[None, None, :, None] * e[:, None, None, :] + ys[None, :, None, None] * nrm[:, None, None, :]
    P, h, w = g.shape[:3]
    mx = np.ascontiguousarray(g[..., 0].reshape(P * h, w), np.float32)
    my = np.ascontiguousarray(g[..., 1].reshape(P * h, w), np.float32)
    rows = 30000 // h * h  # OpenCV's maps hold fewer than 32767 rows
    return np.concatenate([cv2.remap(grey, mx[r : r + rows], my[r : r + rows], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for r in range(0, P * h, rows)]).reshape(P, h, w)


def epipolar_zncc(grey_a: np.ndarray, grey_b: np.ndarray, va: "ViewKeypoints", vb: "ViewKeypoints", ia, ib, T_a_b: np.ndarray, cam_a, cam_b):
    """Sub-pixel positions [P,2] in view b of keypoints ``ia`` of view a, found along their
    epipolar lines near their descriptor matches ``ib``, and which were found [P] bool.

    Each keypoint's patch (``PATCH``, sampled at its sub-pixel position, its x axis along the
    keypoint's epipolar line in a) is scored by ZNCC against b's image along b's line in
    whole-pixel steps (from a's position on a rectified pair, so that patch and line are
    interpolated at the same phase) and on the rows one pixel either side of the line. The
    peak less than ``SEARCH`` px from the descriptor match, refined by a parabola, is kept where
    it scores at least ``ZNCC_MIN``, beats the rows beside it (the match lies within half a
    pixel of the line) and no score along the line more than 2 px from it (``UNIQUE`` px either
    side of the strip's centre) comes within ``ZNCC_MARGIN`` of it: the classical VO's gates.
    Only the position along the line is measured, on a rectified pair the disparity: a match free
    to move across the line slides along slanted edges, and ZNCC, unlike brightness constancy,
    is blind to the cameras' different exposures."""
    ia, ib = np.asarray(ia), np.asarray(ib)
    P = len(ia)
    out, found = np.zeros((P, 2)), np.zeros(P, bool)
    if not P:
        return out, found
    q_b, e_a, e_b, ok = epipolar_directions(cam_a, cam_b, T_a_b, va.bearings[ia], vb.bearings[ib])
    p_a = va.uv[ia]
    # centre b's strip on the line at its descriptor match, in whole steps from a's position along the line
    # (a rectified pair: an integer disparity, so patch and strip are interpolated at the same phase)
    along = np.einsum("pi,pi->p", vb.uv[ib] - q_b, e_b)
    q = q_b + along[:, None] * e_b
    off = np.einsum("pi,pi->p", q - p_a, e_b)
    c_b = q + (np.rint(off) - off)[:, None] * e_b
    w, L = PATCH, PATCH + UNIQUE
    T = _sample(grey_a, p_a, e_a, w, w).reshape(P, -1).astype(np.float64)
    S = _sample(grey_b, c_b, e_b, L, w + 1).astype(np.float64)  # [P, 2w+3, 2L+1]
    T -= T.mean(1, keepdims=True)
    tn = np.linalg.norm(T, axis=1)
    from numpy.lib.stride_tricks import sliding_window_view

    win = sliding_window_view(S, (2 * w + 1, 2 * w + 1), axis=(1, 2)).reshape(P, 3, 2 * UNIQUE + 1, -1)  # [P, 3 rows, 2U+1 shifts, patch]
    wm = win.mean(-1)
    num = np.einsum("prsk,pk->prs", win, T)
    den = np.sqrt(np.maximum((win * win).sum(-1) - win.shape[-1] * wm * wm, 0.0)) * tn[:, None, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        C = np.where(den > 1e-6, num / den, -1.0)
    mid = C[:, 1]  # [P, 2U+1]
    lo, hi = UNIQUE - SEARCH, UNIQUE + SEARCH
    j = lo + np.argmax(mid[:, lo : hi + 1], axis=1)
    rows = np.arange(P)
    best = mid[rows, j]
    on_line = (C[rows, 0, j] < best) & (C[rows, 2, j] < best)
    near = np.abs(np.arange(2 * UNIQUE + 1)[None] - j[:, None]) <= 2
    second = np.where(near, -1.0, mid).max(1)
    good = ok & (tn > 1e-3) & (best >= ZNCC_MIN) & on_line & (second < best - ZNCC_MARGIN) & (j > lo) & (j < hi)
    a_, c_ = mid[rows, np.maximum(j - 1, 0)], mid[rows, np.minimum(j + 1, 2 * UNIQUE)]
    curv = a_ - 2 * best + c_
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(curv < 0, 0.5 * (a_ - c_) / curv, 0.0)
    out = c_b + (j - UNIQUE + frac)[:, None] * e_b
    found = good & np.isfinite(out).all(1)
    return out, found


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

    def _refined(self, a: int, b: int, ia, ib, views, T_a_b: np.ndarray):
        """Bearings in view b of keypoints ``ia`` of view a, each found along its epipolar line
        near its descriptor match ``ib`` (:func:`epipolar_zncc`), and which were found
        (``[P]`` bool). Two independently detected keypoints each carry ~0.3 px of noise (3 % of
        depth at 10 px of disparity), and a match refined with both coordinates free slides
        along slanted edges (2-D Lucas-Kanade was 0.06 px off on a rendered KITTI pair with
        unequal exposures, tests/ba/test_keypoints.py), so only the position along the line is
        measured. A keypoint of b without depth moves to the found position."""
        vb = views[b]
        if not len(ia):
            return vb.bearings[ib], np.zeros(0, bool)
        uv_b, ok = epipolar_zncc(self._grey_f[a], self._grey_f[b], views[a], vb, ia, ib, T_a_b, self._cams[a], self._cams[b])
        bb = vb.bearings[ib].copy()
        if ok.any():
            rays = self._unproject(self._cams[b], uv_b[ok])
            bb[ok] = rays / np.linalg.norm(rays, axis=1, keepdims=True)
            # the found position is the keypoint's (it is where a's patch is) unless its point is already on its old ray (sensor depth)
            move = ~vb.has_depth[ib[ok]]
            idx = ib[ok][move]
            vb.uv[idx], vb.rays[idx], vb.bearings[idx] = uv_b[ok][move], rays[move], bb[ok][move]
        return bb, ok

    def detect(self, images, depths=None) -> list[ViewKeypoints]:
        """Keypoints [C] of one rig frame (``images`` [C] of [H,W,3] in [0,1]; ``depths`` [C]
        of [H,W] m or None)."""
        import cv2

        sift = cv2.SIFT_create(nfeatures=self.features, contrastThreshold=0.02)
        views = []
        grey = [to_grey8(img) for img in images]
        self._grey_f = [img.astype(np.float32) for img in grey]
        for c, img in enumerate(grey):
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
        bb, found = self._refined(a, b, ia, ib, views, T_a_b)
        ba = va.bearings[ia]
        X, s, r = triangulate(T_a_b, ba, bb)
        rng = np.linalg.norm(X, axis=1)
        ok = found & (s > 0) & (r > 0) & (rng < self.max_baselines * baseline) & np.isfinite(rng)
        # each view keeps the point on its own ray, at the triangulated range
        for view, idx, P in ((va, ia, s[:, None] * ba), (vb, ib, r[:, None] * bb)):
            free = ok & ~view.has_depth[idx]
            view.points[idx[free]] = P[free]
        va.partners[b] = (ia[ok], ib[ok])
