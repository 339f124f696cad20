"""The built-in synthetic multi-camera sequence, with exact depth and poses.

A rig (``configs/rig_synthetic.yaml``: front pinhole, left fisheye, right pinhole,
back pinhole) drives down a textured room of boxes and spheres; a Warp ray caster
(:mod:`mcgs_warp.kernels.raycast`) renders colour and exact depth for every camera.
The depth a run sees is a choice (``exact``, ``mono``-like or ``none``); the exact
depth always lands under ``gt/`` for evaluation.
World and body frames: x forward, y left, z up (m). Deterministic for a seed.
"""

from __future__ import annotations

import sys
from importlib import resources
from pathlib import Path

import numpy as np
import warp as wp

from ..errors import InputError
from ..geometry import yaw_pitch_roll
from ..rig import Rig, load_rig
from .mono_prior import PRIOR_MODELS, REALISTIC, SMOOTH, mono_like_depth
from .sequence import FolderSequence, FolderWriter
from .trajectory import Trajectory

RIG_CONFIG = "rig_synthetic.yaml"
STREET_RIG = "rig_street.yaml"
SCENES = ("room", "indoor", "street")
FRAME_RATE = 10.0  # Hz
SPEED = 1.5  # m/s along x


def synthetic_rig(n_cameras: int = 3, config: str = RIG_CONFIG) -> Rig:
    """The first ``n_cameras`` cameras of a packaged rig (default the synthetic room's)."""
    rig = load_rig(resources.files("mcgs_warp.configs") / config)
    if not 1 <= n_cameras <= len(rig):
        raise InputError(None, "--cameras", f"expected 1 to {len(rig)}, got {n_cameras}")
    return rig.subset(range(n_cameras))


def rig_trajectory(n_frames: int) -> Trajectory:
    """Rig body poses ``T_w_b``: forward along x with a gentle weave, yaw and bob."""
    t = np.arange(n_frames) / FRAME_RATE
    T = np.zeros((n_frames, 4, 4))
    T[:, 3, 3] = 1.0
    w = 2 * np.pi / 4.0  # one weave every 4 s
    for k, tk in enumerate(t):
        T[k, :3, :3] = yaw_pitch_roll(0.12 * np.sin(w * tk), 0.02 * np.sin(2 * w * tk), 0.015 * np.cos(w * tk))
        T[k, :3, 3] = [SPEED * tk, 0.4 * np.sin(w * tk), 1.4 + 0.05 * np.sin(2 * w * tk)]
    return Trajectory(t, T)


LOOP_STRAIGHT = 14.0  # m: the full loop's straight legs, along x from x = 0
LOOP_RADIUS = 1.2  # m: its half-turns (the lane |y| < 1.6 m is free of obstacles)
LOOP_FULL = 2 * LOOP_STRAIGHT + 2 * np.pi * LOOP_RADIUS  # m: the full loop's length (35.5 m)
LOOP_STEP = LOOP_FULL / 640  # m per frame at most (0.55 m/s at 10 Hz): 640 frames drive the full loop


def loop_trajectory(n_frames: int, max_step: float = LOOP_STEP) -> Trajectory:
    """Rig body poses ``T_w_b`` of one closed loop through the room: out along y = +r,
    a half-turn, back along y = -r, a half-turn, ending where it started (so the last
    frames revisit the first views). Heading follows the path.

    The rig moves at most ``max_step`` m per frame (default 0.55 m/s), so the distance between
    frames is the same at every length: ``n_frames >= 640`` drive the full loop (14 m legs,
    1.2 m half-turns, 2.65 degrees of heading per frame in them; more frames, slower), fewer
    drive a shorter one (160 frames: 0.67 m legs; 135 frames or fewer a circle, which turns
    faster: 40 frames, 0.35 m radius, 9 degrees per frame). ``max_step=np.inf``: the full loop
    at any length (keyframe-like spacing for tests and benchmarks)."""
    if not max_step > 0:
        raise ValueError(f"loop_trajectory: max_step must be > 0 m, got {max_step}")
    t = np.arange(n_frames) / FRAME_RATE
    perimeter = min(LOOP_FULL, n_frames * max_step)
    r = min(LOOP_RADIUS, perimeter / (2 * np.pi))
    L = max(0.0, (perimeter - 2 * np.pi * r) / 2)
    s = perimeter * np.arange(n_frames) / n_frames  # arc length; frame n would close the loop
    T = np.zeros((n_frames, 4, 4))
    T[:, 3, 3] = 1.0
    for k, sk in enumerate(s):
        if sk < L:  # outbound, y = +r, heading +x
            x, y, yaw = sk, r, 0.0
        elif sk < L + np.pi * r:  # half-turn around (L, 0)
            a = (sk - L) / r
            x, y, yaw = L + r * np.sin(a), r * np.cos(a), -a
        elif sk < 2 * L + np.pi * r:  # back, y = -r, heading -x
            x, y, yaw = L - (sk - L - np.pi * r), -r, -np.pi
        else:  # half-turn around (0, 0) back to the start
            a = (sk - 2 * L - np.pi * r) / r
            x, y, yaw = -r * np.sin(a), -r * np.cos(a), -np.pi - a
        T[k, :3, :3] = yaw_pitch_roll(yaw, 0.02 * np.sin(0.7 * sk), 0.0)
        T[k, :3, 3] = [x, y, 1.4 + 0.05 * np.sin(0.5 * sk)]
    return Trajectory(t, T)


def build_scene(seed: int, device=None):
    """Room, boxes, spheres and materials for ``seed``; returns the Warp ``Scene`` struct."""
    from ..kernels.raycast import make_scene

    rng = np.random.default_rng(seed)
    n_mat = 12
    base = rng.uniform(0.25, 0.95, (n_mat, 3))
    accent = base * rng.uniform(0.15, 0.5, (n_mat, 1))
    freq = rng.uniform(2.0, 7.0, n_mat)
    kind = rng.integers(0, 3, n_mat)
    kind[:3] = [2, 1, 0]  # floor: checker, walls: bricks, ceiling: noise
    # Boxes and spheres on both sides of the driving lane (|y| < 1.6 stays free).
    nb, ns = 26, 12
    side = rng.choice([-1.0, 1.0], nb)
    half = rng.uniform(0.25, 0.8, (nb, 3))
    box_c = np.stack([rng.uniform(-2.0, 29.0, nb), side * rng.uniform(2.2, 4.2, nb), half[:, 2]], 1)
    sph_side = rng.choice([-1.0, 1.0], ns)
    sph_r = rng.uniform(0.25, 0.6, ns)
    sph_c = np.stack([rng.uniform(-2.0, 29.0, ns), sph_side * rng.uniform(2.0, 4.3, ns), rng.uniform(0.6, 3.0, ns)], 1)
    # A few obstacles far ahead in the lane give the front camera depth variety.
    far = np.array([[16.0, 0.5, 0.6], [20.0, -0.8, 1.0], [24.0, 0.3, 0.8]])
    box_c = np.concatenate([box_c, far])
    half = np.concatenate([half, [[0.6, 0.6, 0.6], [0.7, 0.5, 1.0], [0.8, 0.8, 0.8]]])

    yaw = rng.uniform(-0.6, 0.6, len(box_c))
    box_mat = rng.integers(3, n_mat, len(box_c))
    sph_mat = rng.integers(3, n_mat, ns)
    # faces -x, +x, -y, +y: walls; -z: floor; +z: ceiling
    return make_scene((-3.0, -5.0, 0.0), (30.0, 5.0, 4.0), [1, 1, 1, 1, 0, 2], (box_c, half, yaw, box_mat), (sph_c, sph_r, sph_mat), (base, accent, freq, kind), (0.3, 0.5, 0.8), 0.45, 0.55, device=device)


class SceneRenderer:
    """Renders colour and exact depth of every rig camera with the Warp ray caster."""

    def __init__(self, scene, rig: Rig, supersample: int = 2, device=None):
        from ..kernels import Camera
        from ..kernels.raycast import camera_rays_kernel

        self.scene, self.rig, self.ss = scene, rig, supersample
        self.device = wp.get_device(device)
        self.cams = wp.array(rig.warp_cameras(), dtype=Camera, device=self.device)
        self.H = max(c.height for c in rig.cameras)
        self.W = max(c.width for c in rig.cameras)
        C, ss = len(rig), supersample
        self.centre = wp.zeros((C, self.H, self.W), dtype=wp.vec3, device=self.device)
        self.sub = wp.zeros((C, self.H * ss, self.W * ss), dtype=wp.vec3, device=self.device)
        wp.launch(camera_rays_kernel, dim=(C, self.H, self.W), inputs=[self.cams, ss], outputs=[self.centre, self.sub], device=self.device)

    def render(self, T_w_b: np.ndarray):
        """Colour [C,H,W,3] (RGB in [0,1]) and depth [C,H,W] (m) at body pose ``T_w_b`` [4,4],
        or each camera at its own body pose (``T_w_b`` [C,4,4]: cameras that fire at
        different times)."""
        from ..kernels.launch import run_row_bands
        from ..kernels.raycast import raycast_kernel

        C = len(self.rig)
        T_w_c = self.rig.camera_poses(T_w_b)
        T_w_c = T_w_c[np.arange(C), np.arange(C)] if np.ndim(T_w_b) == 3 else T_w_c  # [C,C,4,4] -> camera c at pose c
        poses = wp.array(T_w_c.astype(np.float32), dtype=wp.mat44, device=self.device)
        color = wp.zeros((C, self.H, self.W), dtype=wp.vec3, device=self.device)
        depth = wp.zeros((C, self.H, self.W), dtype=float, device=self.device)

        def band(worker, row0, rows):
            wp.launch(
                raycast_kernel,
                dim=(C, rows, self.W),
                inputs=[self.scene, self.cams, poses, self.centre, self.sub, self.ss, row0],
                outputs=[color, depth],
                device=self.device,
            )

        run_row_bands(self.device, self.H, band)
        return color.numpy(), depth.numpy()


def pose_at(traj: Trajectory, t: float) -> np.ndarray:
    """The body pose [4,4] of ``traj`` at time ``t`` (s), interpolated between its poses and
    extrapolated along the first or last motion beyond its ends."""
    from .trajectory import bracket, interpolate_pose

    a, b, u = bracket(traj.timestamps, t, clamp=False)
    return interpolate_pose(traj.poses[a], traj.poses[b], u)


def generate(out, n_cameras: int = 3, n_frames: int = 40, seed: int = 0, device=None, progress: bool = True, depth: str = "exact", trajectory: str | Trajectory = "forward", rig: Rig | None = None, realism: str = "none", realism_config=None, mono_prior: str = "smooth", scene: str = "room", camera_delays=None) -> FolderSequence:
    """Write the synthetic sequence to ``out`` in our folder format and open it.

    ``scene``: ``room`` (the textured room, this module, the same for every seed but its
    objects), ``indoor`` (a room or corridor and a drive that vary with the seed,
    :mod:`mcgs_warp.data.indoor`; ``forward`` is that drive) or ``street`` (a road between
    façades under a sky, :mod:`mcgs_warp.data.street`: its own rig, ``configs/rig_street.yaml``,
    unless ``rig`` is given, and ``n_cameras`` of it; the ``forward`` trajectory drives down
    the road at 10 m/s).

    ``depth``: what ``cam<i>/depth`` holds: ``exact`` (ray-cast depth), ``mono`` (a
    monocular-style prior, :func:`~mcgs_warp.data.mono_prior.mono_like_depth` with the
    ``mono_prior`` error model, ``smooth`` or ``realistic``) or ``none`` (no depth folder). The
    exact depth always goes to ``gt/cam<i>/depth`` for evaluation; ``metadata.yaml``
    records the kind. ``trajectory``: ``forward`` (down the room with a weave,
    :func:`rig_trajectory`), ``loop`` (one closed loop, :func:`loop_trajectory`) or a
    :class:`Trajectory` of body poses (its length sets the frame count). ``rig``:
    cast this rig instead of the built-in one's first ``n_cameras`` (body x forward, y left,
    z up; pixels of a camera without a ray, such as a fisheye's corners beyond 90 degrees,
    come out black with depth 0). ``realism``: ``none`` (the perfect render) or ``camera``
    (motion blur, vignetting, per-frame gains, noise, JPEG: :mod:`mcgs_warp.data.realism`,
    settings ``realism_config``, a :class:`~mcgs_warp.data.realism.CameraRealism`; the gains
    go to ``gt/gains.txt``). ``camera_delays`` [C] (s): each camera's image is taken that long
    after its frame's timestamp, along the trajectory (extrapolated past its ends), while the
    folder stamps the frames as synchronized: cameras whose exposures are centred at different
    times (unequal exposure times, or a surround rig firing camera by camera)."""
    from .realism import REALISM, CameraRealism, camera_image, gains, image_motion, vignetting

    if mono_prior not in PRIOR_MODELS:
        raise InputError(None, "--mono-prior", f"expected one of {' | '.join(PRIOR_MODELS)}, got {mono_prior!r}")
    errors = REALISTIC if mono_prior == "realistic" else SMOOTH
    if realism not in REALISM:
        raise InputError(None, "--realism", f"expected one of {' | '.join(REALISM)}, got {realism!r}")
    if isinstance(trajectory, Trajectory):
        n_frames = len(trajectory.timestamps)
        if trajectory.poses.shape != (n_frames, 4, 4):
            raise ValueError(f"generate: the trajectory has {n_frames} timestamps but poses of shape {trajectory.poses.shape}; expected ({n_frames}, 4, 4)")
    if n_frames < 2:
        raise InputError(None, "--frames", f"expected at least 2, got {n_frames}")
    if depth not in ("exact", "mono", "none"):
        raise InputError(None, "--depth", f"expected exact, mono or none, got {depth!r}")
    if scene not in SCENES:
        raise InputError(None, "--scene", f"expected one of {' | '.join(SCENES)}, got {scene!r}")
    if scene != "room" and trajectory == "loop":
        raise InputError(None, "--trajectory", f"loop drives the built-in room only (--scene room), not --scene {scene}")
    if isinstance(trajectory, Trajectory):
        traj = trajectory
    elif trajectory in ("forward", "loop"):
        if scene == "street":
            from .street import street_trajectory

            traj = street_trajectory(n_frames, FRAME_RATE, seed)
        elif scene == "indoor":
            from .indoor import indoor_trajectory

            traj = indoor_trajectory(n_frames, seed, FRAME_RATE)
        else:
            traj = rig_trajectory(n_frames) if trajectory == "forward" else loop_trajectory(n_frames)
    else:
        raise InputError(None, "--trajectory", f"expected forward or loop, got {trajectory!r}")
    rig = synthetic_rig(n_cameras, STREET_RIG if scene == "street" else RIG_CONFIG) if rig is None else rig
    if scene == "street":
        from .street import build_street, road_end

        world = build_street(seed, device, road_end(len(traj), FRAME_RATE))
    elif scene == "indoor":
        from .indoor import build_indoor

        world = build_indoor(seed, device)
    else:
        world = build_scene(seed, device)
    renderer = SceneRenderer(world, rig, device=device)
    writer = FolderWriter(out, rig, depth_kind=depth)
    rng = np.random.default_rng(1000 + seed)
    if realism == "camera":
        cfg = realism_config or CameraRealism()
        sensor_rng = np.random.default_rng(2000 + seed)  # its own stream: the depth prior stays as without realism
        gain = gains(n_frames, len(rig), cfg, sensor_rng)
        vignettes = [vignetting(c, cfg.vignette) for c in rig.cameras]
        rays, structs = renderer.centre.numpy(), rig.warp_cameras()
        T_w_c = rig.camera_poses(traj.poses)  # [K,C,4,4]
    if camera_delays is not None and len(camera_delays) != len(rig):
        raise ValueError(f"generate: camera_delays has {len(camera_delays)} values for a rig of {len(rig)} cameras")
    for k in range(n_frames):
        at = traj.poses[k] if camera_delays is None or not np.any(camera_delays) else np.stack([pose_at(traj, traj.timestamps[k] + d) for d in camera_delays])
        color, exact = renderer.render(at)
        exact = [exact[i, : c.height, : c.width] for i, c in enumerate(rig.cameras)]
        seen = [mono_like_depth(d, rng, errors) for d in exact] if depth == "mono" else exact if depth == "exact" else None
        images = [color[i, : c.height, : c.width] for i, c in enumerate(rig.cameras)]
        if realism == "camera":
            nxt = k + 1 if k + 1 < n_frames else k - 1  # the motion around frame k
            fraction = cfg.exposure_s / (traj.timestamps[nxt] - traj.timestamps[k])  # of the motion to frame nxt (negative: backwards)
            for i, c in enumerate(rig.cameras):
                move = image_motion(rays[i, : c.height, : c.width], exact[i], structs[i], np.linalg.inv(T_w_c[nxt, i]) @ T_w_c[k, i])
                images[i] = camera_image(images[i], fraction * move, vignettes[i], gain[k, i], cfg, sensor_rng)
        writer.write_frame(k, images, seen, gt_depths=exact)
        if progress and ((k + 1) % 10 == 0 or k + 1 == n_frames):
            print(f"\rsynth: {k + 1}/{n_frames} frames x {len(rig)} cameras", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    writer.finish(traj.timestamps, traj)
    if realism == "camera":
        from ..io import atomic_write

        with atomic_write(Path(out) / "gt" / "gains.txt") as f:
            f.write("# synth --realism camera: auto-exposure gain per frame (rows) and camera (columns): image = gain x render (before vignetting and noise)\n")
            f.writelines(" ".join(f"{g:.6f}" for g in row) + "\n" for row in gain)
    return FolderSequence(Path(out))
