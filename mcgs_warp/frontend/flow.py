"""Dense correspondences for MCBA edges, behind a small interface.

A :class:`FlowProvider` turns the edges of the keyframe buffer into targets
``p~_ij`` (the pixel of view (j, cj) matching each reduced-grid pixel of view
(i, ci), in reduced-grid coordinates) and confidences ``w_ij`` in [0, 1]. The
paper uses a learned recurrent flow network (RFT); here:

* :class:`DISFlow` — OpenCV's DIS optical flow, forward and backward, with the
  forward-backward consistency as confidence; any learned flow can replace it by
  implementing ``flow(image_a, image_b)``.
* :class:`GroundTruthFlow` — exact correspondences from depth and poses (synthetic
  data, tests), with occlusions removed by a depth test.
"""

from __future__ import annotations

import numpy as np

from ..buffer import KeyframeBuffer, grid_pixels


class FlowProvider:
    def correspondences(self, buffer: KeyframeBuffer, edges: np.ndarray):
        """``targets`` [E,h,w,2] (reduced-grid pixels of view (j, cj)) and ``weights`` [E,h,w]."""
        raise NotImplementedError


def to_reduced(uv: np.ndarray, stride: int) -> np.ndarray:
    return (uv - stride // 2) / stride


class DISFlow(FlowProvider):
    """OpenCV DIS flow with forward-backward consistency ``w = exp(-(e / sigma)^2)``
    (``e``: forward-backward error in full-resolution pixels)."""

    def __init__(self, preset: str = "medium", sigma: float = 1.0):
        import cv2

        presets = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST, "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
        self.dis = cv2.DISOpticalFlow_create(presets[preset])
        self.sigma = sigma

    @staticmethod
    def _grey(img):
        import cv2

        return cv2.cvtColor((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2GRAY)

    def flow(self, image_a: np.ndarray, image_b: np.ndarray):
        """Dense flow [H,W,2] from a to b (px) and its confidence [H,W] in [0,1]."""
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
        back = cv2.remap(bwd, u + fwd[..., 0], v + fwd[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1e4)
        err = np.linalg.norm(fwd + back, axis=-1)
        h0, w0 = image_a.shape[:2]
        return fwd[:h0, :w0], np.exp(-((err[:h0, :w0] / self.sigma) ** 2))

    def correspondences(self, buffer: KeyframeBuffer, edges: np.ndarray):
        E, s = len(edges), buffer.stride
        targets = np.zeros((E, buffer.h, buffer.w, 2), np.float32)
        weights = np.zeros((E, buffer.h, buffer.w), np.float32)
        for e, (i, ci, j, cj) in enumerate(edges[:, :4]):
            flow, conf = self.flow(buffer.images[i][ci], buffer.images[j][cj])
            spec = buffer.rig.cameras[ci]
            uv = grid_pixels(spec, s)
            ui, vi = uv[..., 0].astype(int), uv[..., 1].astype(int)
            h, w = uv.shape[:2]
            t = uv + flow[vi, ui]  # full-resolution pixel in view (j, cj)
            targets[e, :h, :w] = to_reduced(t, s)
            cam_j = buffer.rig.cameras[cj]
            inside = (t[..., 0] >= 0) & (t[..., 0] <= cam_j.width - 1) & (t[..., 1] >= 0) & (t[..., 1] <= cam_j.height - 1)
            weights[e, :h, :w] = conf[vi, ui] * inside
        return targets, weights


class GroundTruthFlow(FlowProvider):
    """Exact correspondences from full-resolution depth maps and poses.

    ``depths[k][c]`` [H,W] (m, camera-model depth) and ``T_w_b`` [K,4,4] are the true
    values for the buffer's keyframes. A correspondence counts (weight 1) where the
    point lands inside view (j, cj) and that view's depth map sees the same surface
    (within ``rel_tol``), else weight 0."""

    def __init__(self, depths, T_w_b: np.ndarray, rel_tol: float = 0.02):
        self.depths = depths
        self.T_w_b = np.asarray(T_w_b, dtype=np.float64)
        self.rel_tol = rel_tol

    def correspondences(self, buffer: KeyframeBuffer, edges: np.ndarray):
        from ..kernels import reference

        E, s = len(edges), buffer.stride
        rays = buffer.rays.numpy().astype(np.float64)
        targets = np.zeros((E, buffer.h, buffer.w, 2), np.float32)
        weights = np.zeros((E, buffer.h, buffer.w), np.float32)
        full_cams = [c.warp_camera() for c in buffer.rig.cameras]
        for e, (i, ci, j, cj) in enumerate(edges[:, :4]):
            spec_i = buffer.rig.cameras[ci]
            uv = grid_pixels(spec_i, s)
            h, w = uv.shape[:2]
            z = self.depths[i][ci][uv[..., 1].astype(int), uv[..., 0].astype(int)].astype(np.float64)
            X = rays[ci, :h, :w] * z[..., None]
            T = np.linalg.inv(self.T_w_b[j] @ buffer.rig.cameras[cj].T_b_c) @ self.T_w_b[i] @ spec_i.T_b_c
            Xj = X.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
            cam = full_cams[cj]
            ok = (z.reshape(-1) > 0) & reference.in_domain(cam, Xj)
            p = reference.project(cam, np.where(ok[:, None], Xj, [0.0, 0.0, 1.0]))
            inside = ok & (p[:, 0] >= 0) & (p[:, 0] <= cam.width - 1) & (p[:, 1] >= 0) & (p[:, 1] <= cam.height - 1)
            pr = np.round(np.where(inside[:, None], p, 0)).astype(int)
            seen = self.depths[j][cj][pr[:, 1], pr[:, 0]]
            pred = reference.depth(cam, Xj)
            visible = inside & (np.abs(seen - pred) <= self.rel_tol * pred)
            targets[e, :h, :w] = to_reduced(p, s).reshape(h, w, 2)
            weights[e, :h, :w] = visible.reshape(h, w)
        return targets, weights
