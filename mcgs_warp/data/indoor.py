"""Indoor worlds that vary with the seed (``synth --scene indoor``): a different place driven a
different way for every seed, so that a held-out seed tests generalization.

The seed draws the room (length 20-45 m, width 4-12 m: below 6 m a corridor, height 2.6-4.5 m),
its obstacles (boxes and spheres beside the driving lane, more in wide rooms), the materials
(texture kind, colours, frequency scale; corridors often low-contrast), the light (direction,
ambient and diffuse strength) and the drive (speed 0.8-2.2 m/s from the first frame on, weave,
heading swing, height 1.0-1.8 m, and sometimes a pause of 0.5-1.5 s standing still). The
built-in room (``--scene room``) stays what it always was; this module never changes it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import yaw_pitch_roll
from .trajectory import Trajectory

START_X = -2.0  # m: the drive starts here, 1 m from the back wall


@dataclass(frozen=True)
class IndoorLayout:
    length: float  # m along x (from x = START_X - 1)
    half_width: float  # m: the room spans |y| < half_width
    height: float  # m
    speed: float  # m/s while moving
    weave: float  # m: lateral amplitude of the drive
    period: float  # s of one weave
    yaw_swing: float  # rad: heading amplitude
    rig_height: float  # m
    pause_start: int  # frame where the rig stops (-1: never)
    pause_frames: int
    low_texture: bool  # walls of low contrast

    @property
    def corridor(self) -> bool:
        return self.half_width < 3.0


def indoor_layout(seed: int) -> IndoorLayout:
    """The room and the drive that ``seed`` draws."""
    rng = np.random.default_rng(20_000 + seed)
    half_width = float(rng.uniform(2.0, 6.0))
    corridor = half_width < 3.0
    pause = rng.random() < 0.5
    height = float(rng.uniform(2.6, 4.5))
    return IndoorLayout(
        length=float(rng.uniform(20.0, 45.0)),
        half_width=half_width,
        height=height,
        speed=float(rng.uniform(0.8, 2.2)),
        weave=float(rng.uniform(0.0, min(0.5, half_width - 1.6))),
        period=float(rng.uniform(3.0, 8.0)),
        yaw_swing=float(rng.uniform(0.02, 0.18)),
        rig_height=float(rng.uniform(1.0, min(1.8, height - 0.8))),
        pause_start=int(rng.integers(8, 25)) if pause else -1,
        pause_frames=int(rng.integers(5, 16)) if pause else 0,
        low_texture=bool(corridor and rng.random() < 0.7 or rng.random() < 0.15),
    )


def indoor_trajectory(n_frames: int, seed: int, rate: float = 10.0) -> Trajectory:
    """Rig body poses ``T_w_b`` of the drive ``seed`` draws: full speed from the first frame,
    standing still during its pause, slowed only if the room is too short for ``n_frames``."""
    lay = indoor_layout(seed)
    t = np.arange(n_frames) / rate
    moving = np.ones(n_frames, bool)
    if lay.pause_start >= 0:
        moving[lay.pause_start : lay.pause_start + lay.pause_frames] = False
    room_left = lay.length - 4.0  # stop 3 m before the far wall
    steps = max(int(moving[1:].sum()), 1)
    speed = min(lay.speed, room_left * rate / steps)
    s = np.concatenate([[0.0], np.cumsum(moving[1:] * speed / rate)])  # arc length
    w = 2 * np.pi / lay.period
    T = np.zeros((n_frames, 4, 4))
    T[:, 3, 3] = 1.0
    for k in range(n_frames):
        phase = w * s[k] / max(speed, 1e-9)  # the weave follows the distance driven (a pause holds it)
        T[k, :3, :3] = yaw_pitch_roll(lay.yaw_swing * np.sin(phase), 0.02 * np.sin(2 * phase), 0.01 * np.cos(phase))
        T[k, :3, 3] = [START_X + s[k], lay.weave * np.sin(phase), lay.rig_height]
    return Trajectory(t, T)


def build_indoor(seed: int, device=None):
    """The Warp ``Scene`` of the room ``seed`` draws (module docstring)."""
    from ..kernels.raycast import make_scene

    lay = indoor_layout(seed)
    rng = np.random.default_rng(30_000 + seed)
    n_mat = 12
    base = rng.uniform(0.25, 0.95, (n_mat, 3))
    accent = base * rng.uniform(0.15, 0.5, (n_mat, 1))
    freq = rng.uniform(2.0, 7.0, n_mat) * rng.uniform(0.4, 1.6)  # texture scale of the whole world
    kind = rng.integers(0, 3, n_mat)
    kind[:3] = rng.integers(0, 3, 3)  # floor, walls, ceiling
    if lay.low_texture:
        accent[1] = base[1] * rng.uniform(0.85, 0.95)  # walls: a faint texture only
        accent[2] = base[2] * 0.9
    x0, x1 = START_X - 1.0, START_X - 1.0 + lay.length
    lane = lay.weave + 1.3  # obstacles keep |y| > lane
    room = max(lay.half_width - lane, 0.0)
    nb = int(rng.integers(4, 10) + (room > 1.0) * lay.length * rng.uniform(0.3, 0.8))
    ns = int(rng.integers(2, 6) + (room > 1.0) * lay.length * rng.uniform(0.1, 0.3))
    half = rng.uniform(0.2, 0.7, (nb, 3))
    half[:, 1] = np.minimum(half[:, 1], np.maximum(room / 2, 0.1))
    half[:, 2] = np.minimum(half[:, 2], lay.height / 2 - 0.1)
    side = rng.choice([-1.0, 1.0], nb)
    y_box = side * np.clip(lane + half[:, 1] + rng.uniform(0.0, max(room - 2 * half[:, 1].max(), 0.0), nb), None, lay.half_width - half[:, 1])
    box_c = np.stack([rng.uniform(x0 + 1.0, x1 - 1.0, nb), y_box, half[:, 2]], 1)
    r = rng.uniform(0.15, 0.5, ns)
    r = np.minimum(r, np.maximum(room / 2, 0.1))
    side_s = rng.choice([-1.0, 1.0], ns)
    sph_c = np.stack([rng.uniform(x0 + 1.0, x1 - 1.0, ns), side_s * np.minimum(lane + r + rng.uniform(0, max(room, 0.0), ns), lay.half_width - r), rng.uniform(0.5, lay.height - 0.5, ns)], 1)

    yaw = rng.uniform(-0.6, 0.6, nb)
    box_mat, sph_mat = rng.integers(3, n_mat, nb), rng.integers(3, n_mat, ns)
    light = (rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.3, 1.0))
    ambient = float(rng.uniform(0.3, 0.6))
    diffuse = float(rng.uniform(0.7, 1.0) - ambient)
    return make_scene((x0, -lay.half_width, 0.0), (x1, lay.half_width, lay.height), [1, 1, 1, 1, 0, 2], (box_c, half, yaw, box_mat), (sph_c, r, sph_mat), (base, accent, freq, kind), light, ambient, diffuse, device=device)
