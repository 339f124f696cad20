"""The keyframe buffer: the one place holding what tracking and mapping share.

Per keyframe: timestamp, source frame index, full-resolution images (host, for flow
and mapping: 8-bit where that holds them exactly, see :func:`compact_image`), and on the buffer's Warp device the rig pose ``T_w_b``, the affine
exposures and, per camera, inverse depth on the reduced grid, the depth prior (sensor
or monocular depth, m, 0 = none), its confidence and its JDSA scale grid (the scaled
prior ``depth_prior * bilinear(scales)`` is derived when needed, on the device:
:func:`mcgs_warp.ba.jdsa.scaled_prior`). Full-resolution mapping depth targets are host
arrays, uploaded by the mapping loss when they change. As in DROID-SLAM's
``DepthVideo`` there are no copies of poses elsewhere: stages read and write these.

Reduced grid: pixel ``(u', v')`` of a camera at ``stride`` s is full-resolution
pixel ``(s u' + s/2, s v' + s/2)`` (integer for even s), so samples of full-res
images, depths and flow fields are exact; see :func:`reduced_camera`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .geometry import matrix_to_transform7, transform7_to_matrix
from .rig import CameraSpec, Rig


def reduced_camera(spec: CameraSpec, stride: int, offset: float | None = None) -> CameraSpec:
    """The camera seen on the reduced grid (same model and distortion, scaled intrinsics):
    pixel ``u'`` is full-resolution ``stride u' + offset`` (default ``stride // 2``, the
    grid's samples; ``(stride - 1) / 2`` for an image downsampled by area averaging)."""
    from .kernels.camera import equirectangular_intrinsics

    fx, fy, cx, cy = spec.intrinsics if spec.intrinsics is not None else equirectangular_intrinsics(spec.width, spec.height)
    o = stride // 2 if offset is None else offset
    return CameraSpec(
        spec.name, spec.model, spec.width // stride, spec.height // stride,
        (fx / stride, fy / stride, (cx - o) / stride, (cy - o) / stride), spec.distortion, spec.T_b_c, spec.time_offset,
    )  # fmt: skip


def compact_image(image: np.ndarray) -> np.ndarray:
    """An RGB image [H,W,3] in [0,1] as the buffer keeps it: uint8 when every value is
    exactly ``n / 255`` (what the readers make of an 8-bit file: a quarter of the float32's
    memory, and :func:`float_image` gives back the same float32 bit for bit), else float32
    as it is (resampled or synthetic colours, a test's edits: no precision is lost); ``None`` stays."""
    if image is None:
        return None
    image = np.asarray(image)
    if image.dtype == np.uint8:
        return image
    image = np.asarray(image, np.float32)
    with np.errstate(invalid="ignore"):
        n = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return n if np.array_equal(float_image(n), image) else image


def float_image(image: np.ndarray) -> np.ndarray:
    """A stored image (:func:`compact_image`) as float32 RGB in [0,1], as the readers give it."""
    return image.astype(np.float32) / 255.0 if image is not None and image.dtype == np.uint8 else image


def grid_pixels(spec: CameraSpec, stride: int) -> np.ndarray:
    """Full-resolution pixel coordinates [h,w,2] (u, v) of the reduced grid."""
    h, w = spec.height // stride, spec.width // stride
    o = stride // 2
    v, u = np.mgrid[0:h, 0:w]
    return np.stack([u * stride + o, v * stride + o], -1).astype(np.float64)


class KeyframeBuffer:
    """Keyframe state (module docstring). ``capacity``: keyframe slots allocated at first; the
    device arrays double when a keyframe needs more, so memory follows the keyframes a run
    has, not the frames of its sequence."""

    def __init__(self, rig: Rig, stride: int = 8, capacity: int = 16, scale_grid=(4, 6), device=None):
        from .kernels import Camera
        from .kernels.ba import grid_rays_kernel

        self.rig = rig
        self.stride = stride
        self.device = wp.get_device(device)
        self.reduced = [reduced_camera(c, stride) for c in rig.cameras]
        self.h = max(c.height for c in self.reduced)
        self.w = max(c.width for c in self.reduced)
        C = len(rig)
        self.cameras = wp.array([c.warp_camera() for c in self.reduced], dtype=Camera, device=self.device)
        self.T_b_c = wp.array(matrix_to_transform7(np.stack([c.T_b_c for c in rig.cameras])).astype(np.float32), dtype=wp.transform, device=self.device)
        self.rays = wp.zeros((C, self.h, self.w), dtype=wp.vec3, device=self.device)
        wp.launch(grid_rays_kernel, dim=(C, self.h, self.w), inputs=[self.cameras], outputs=[self.rays], device=self.device)
        self.scale_grid = tuple(scale_grid)
        #: keyframe -> full-resolution mapping depth targets per camera ([H,W] m, 0 = none;
        #: ``None`` for a camera without); a keyframe is mapped once it has an entry, and a
        #: new list (not an edited one) is what tells the mapping loss to re-upload it
        self.targets: dict[int, list] = {}
        self.timestamps: list[float] = []
        self.frame_index: list[int] = []
        #: keyframe -> per camera its image as stored (:func:`compact_image`); read it with :meth:`image`
        self.images: list[list[np.ndarray]] = []
        self._full_rays = None
        self.capacity = 0
        self._grow(max(1, int(capacity)))

    def _grow(self, capacity: int) -> None:
        """Reallocate the per-keyframe device arrays with ``capacity`` slots, keeping the
        keyframes held so far; new slots take the defaults (zeros; prior confidence and JDSA
        scales 1). Everything reads these arrays through the buffer's attributes, so nothing
        keeps the old ones."""
        C, dev, K = len(self.rig), self.device, len(self)
        grid = (capacity, C, self.h, self.w)
        new = {
            "poses": wp.zeros(capacity, dtype=wp.transform, device=dev),  # T_w_b
            "disp": wp.zeros(grid, dtype=float, device=dev),
            "depth_prior": wp.zeros(grid, dtype=float, device=dev),  # m, 0 = none
            "prior_conf": wp.full(grid, 1.0, dtype=float, device=dev),  # its weight in [0,1]
            "scales": wp.full((capacity, C) + self.scale_grid, 1.0, dtype=wp.float64, device=dev),  # JDSA scale grids
            "exposure": wp.zeros((capacity, C, 2), dtype=float, device=dev),  # per image (log a, b): colour a * C + b
        }
        for name, arr in new.items():
            if K:
                wp.copy(arr[:K], getattr(self, name)[:K])
            setattr(self, name, arr)
        self.capacity = capacity

    @property
    def full_rays(self) -> wp.array:
        """Unit-depth rays [C,H,W] (vec3, on the device) of every full-resolution pixel of each
        camera, padded to the largest; made on first use and shared by the mapping loss
        (normals) and the guided flow (reprojection)."""
        if self._full_rays is None:
            from .kernels import Camera
            from .kernels.ba import grid_rays_kernel

            cams = wp.array([c.warp_camera() for c in self.rig.cameras], dtype=Camera, device=self.device)
            shape = (len(self.rig), max(c.height for c in self.rig.cameras), max(c.width for c in self.rig.cameras))
            rays = wp.zeros(shape, dtype=wp.vec3, device=self.device)
            wp.launch(grid_rays_kernel, dim=shape, inputs=[cams], outputs=[rays], device=self.device)
            self._full_rays = rays  # only once filled: another thread may be asking too
        return self._full_rays

    def __len__(self) -> int:
        return len(self.timestamps)

    def add(self, frame_index: int, timestamp: float, images, T_w_b, disp, depth_prior=None, prior_conf=None) -> int:
        """Append a keyframe: ``disp`` [C,h,w] inverse depth (1/m), ``depth_prior`` [C,h,w] (m, 0 = none)
        and its confidence ``prior_conf`` [C,h,w] in [0,1] (default: 1 where there is a prior)."""
        k = len(self)
        if k >= self.capacity:
            self._grow(2 * self.capacity)
        self.timestamps.append(float(timestamp))
        self.frame_index.append(int(frame_index))
        self.images.append([compact_image(im) for im in images])
        self.set_poses(np.asarray(T_w_b)[None], start=k)
        self.disp[k].assign(np.asarray(disp, dtype=np.float32))
        if depth_prior is not None:
            self.depth_prior[k].assign(np.asarray(depth_prior, dtype=np.float32))
            if prior_conf is None:
                self.prior_conf[k].fill_(1.0)
            else:
                self.prior_conf[k].assign(np.asarray(prior_conf, dtype=np.float32))
        return k

    def image(self, k: int, c: int) -> np.ndarray:
        """Keyframe ``k``'s image of camera ``c``: float32 RGB [H,W,3] in [0,1]."""
        return float_image(self.images[k][c])

    def keyframe_images(self, k: int) -> list:
        """Keyframe ``k``'s images, one per camera (:meth:`image`)."""
        return [self.image(k, c) for c in range(len(self.images[k]))]

    def get_poses(self) -> np.ndarray:
        """Rig poses ``T_w_b`` [K,4,4] of the keyframes."""
        return transform7_to_matrix(self.poses.numpy()[: len(self)])

    def set_poses(self, T_w_b: np.ndarray, start: int = 0) -> None:
        t = matrix_to_transform7(np.asarray(T_w_b)).astype(np.float32)
        wp.copy(self.poses, wp.array(t, dtype=wp.transform, device=self.device), dest_offset=start, count=len(t))

    def depth(self, k: int) -> np.ndarray:
        """Depth [C,h,w] (m, 0 where unknown) of keyframe ``k``."""
        d = self.disp.numpy()[k]
        return np.where(d > 0, 1.0 / np.maximum(d, 1e-12), 0.0)
