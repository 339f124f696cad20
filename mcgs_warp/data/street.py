"""The street scene of the synthetic benchmark (``synth --scene street``).

A straight road (x forward, y left, z up; the ground is z = 0) between rows of façades, with
cars parked along both kerbs, poles and trees on the pavements, and a sky (no depth) above:
depth from about 1 m (a parked car beside a side camera) to beyond 100 m (down the road; our
depth PNGs hold up to 65.5 m, so ``gt/`` has none beyond), driven at 10 m/s
by a rig like Waymo's (``configs/rig_street.yaml``: front, front-left and front-right pinhole
cameras whose views overlap a little). Everything but the layout rule is drawn from the seed.
"""

from __future__ import annotations

import numpy as np

from ..geometry import yaw_pitch_roll
from .trajectory import Trajectory

RIG_CONFIG = "rig_street.yaml"
SPEED = 10.0  # m/s
ROAD_HALF = 5.0  # m: the carriageway spans |y| < 5: two 3 m lanes, and cars parked along both kerbs
LANE = 1.5  # m: the rig drives along y = -LANE (the right lane), cars are parked at |y| > 3.1
PAVEMENT = 3.0  # m: pavement width beside it, façades beyond
CAMERA_HEIGHT = 1.6  # m: the rig body above the road
ROAD_START, ROAD_END = -30.0, 260.0  # m along x: the road of a drive of up to 220 frames (at 10 Hz)
SIGHT = 40.0  # m of road kept ahead of the drive's last pose


def road_end(n_frames: int, rate: float = 10.0) -> float:
    """Where the road of a drive of ``n_frames`` at ``rate`` Hz ends (m along x): :data:`ROAD_END`,
    or farther where the drive would come within :data:`SIGHT` of it (a 300-frame drive is 300 m
    long). Drives that fit keep the standard road, so their layouts stay what a seed gave."""
    return max(ROAD_END, SPEED * max(n_frames - 1, 0) / rate + SIGHT)


def street_trajectory(n_frames: int, rate: float = 10.0, seed: int = 0) -> Trajectory:
    """Rig body poses ``T_w_b`` down the right lane (y = -:data:`LANE`) at :data:`SPEED` with a gentle lane weave
    (amplitude and period from the seed) and its heading following the path."""
    rng = np.random.default_rng(10_000 + seed)
    amp, period = rng.uniform(0.1, 0.3), rng.uniform(4.0, 8.0)
    t = np.arange(n_frames) / rate
    x = SPEED * t
    w = 2 * np.pi / period
    y = -LANE + amp * np.sin(w * t)
    yaw = np.arctan2(amp * w * np.cos(w * t), SPEED)
    T = np.zeros((n_frames, 4, 4))
    T[:, 3, 3] = 1.0
    for k in range(n_frames):
        T[k, :3, :3] = yaw_pitch_roll(yaw[k], 0.005 * np.sin(3 * w * t[k]), 0.0)
        T[k, :3, 3] = [x[k], y[k], CAMERA_HEIGHT]
    return Trajectory(t, T)


def build_street(seed: int, device=None, end: float = ROAD_END):
    """Road, façades, parked cars, poles, trees and materials for ``seed``, the road ending at
    ``end`` (m along x, :func:`road_end`): the Warp ``Scene``."""
    from ..kernels.raycast import make_scene

    rng = np.random.default_rng(seed)
    # materials: 0 road (fine noise), 1 pavement (checker of slabs), then façades, cars, poles, crowns
    base = [[0.32, 0.32, 0.34], [0.62, 0.6, 0.56]]
    accent = [[0.12, 0.12, 0.13], [0.4, 0.38, 0.35]]
    freq, kind = [6.0, 2.0], [0, 2]
    n_facade, n_car = 8, 6
    for _ in range(n_facade):
        b = rng.uniform(0.35, 0.9, 3)
        base.append(b), accent.append(b * rng.uniform(0.2, 0.5)), freq.append(rng.uniform(1.0, 4.0)), kind.append(int(rng.integers(0, 2)))
    for _ in range(n_car):
        b = rng.uniform(0.1, 0.95, 3)
        base.append(b), accent.append(b * 0.3), freq.append(rng.uniform(3.0, 8.0)), kind.append(0)
    base += [[0.45, 0.45, 0.45], [0.25, 0.5, 0.2]]  # poles, tree crowns
    accent += [[0.2, 0.2, 0.2], [0.08, 0.2, 0.05]]
    freq += [5.0, 3.0]
    kind += [0, 0]
    pole_mat, crown_mat = len(base) - 2, len(base) - 1

    centres, halves, yaws, mats = [], [], [], []

    def box(c, h, m, yaw=0.0):
        centres.append(c), halves.append(h), mats.append(m), yaws.append(yaw)

    # façades: blocks of 8-25 m along both sides, 5-16 m tall, with gaps
    for side in (-1.0, 1.0):
        x = ROAD_START
        while x < end:
            length = rng.uniform(8.0, 25.0)
            depth, height = rng.uniform(6.0, 12.0), rng.uniform(5.0, 16.0)
            front = ROAD_HALF + PAVEMENT + rng.uniform(0.0, 1.5)
            box([x + length / 2, side * (front + depth / 2), height / 2], [length / 2 - 0.2, depth / 2, height / 2], 2 + int(rng.integers(0, n_facade)))
            x += length + rng.uniform(0.0, 4.0)
    # pavements: kerbs 12 cm above the road
    for side in (-1.0, 1.0):
        box([(ROAD_START + end) / 2, side * (ROAD_HALF + PAVEMENT / 2), 0.06], [(end - ROAD_START) / 2, PAVEMENT / 2, 0.06], 1)
    # a block across the far end of the road: depth beyond 100 m down the road
    box([end + 20.0, 0.0, 15.0], [10.0, 30.0, 15.0], 2 + int(rng.integers(0, n_facade)))
    # parked cars along both kerbs (none beside the start of the rig's lane for the first metres)
    for side in (-1.0, 1.0):
        x = ROAD_START + rng.uniform(0.0, 6.0)
        while x < end - 10:
            if rng.random() < 0.7:
                box([x, side * (ROAD_HALF - 1.0), 0.75], [2.1, 0.9, 0.75], 2 + n_facade + int(rng.integers(0, n_car)), rng.normal(0.0, 0.03))
            x += rng.uniform(5.5, 9.0)
    # poles and trees on the pavements
    spheres, radii, sphere_mats = [], [], []
    for side in (-1.0, 1.0):
        x = ROAD_START + rng.uniform(0.0, 10.0)
        while x < end:
            y = side * (ROAD_HALF + 0.6)
            if rng.random() < 0.5:
                box([x, y, 2.5], [0.08, 0.08, 2.5], pole_mat)
            else:
                box([x, y, 1.5], [0.15, 0.15, 1.5], pole_mat)
                r = rng.uniform(1.2, 2.0)
                spheres.append([x, y, 3.0 + r * 0.8]), radii.append(r), sphere_mats.append(crown_mat)
            x += rng.uniform(9.0, 18.0)

    sun = (rng.uniform(-0.5, 0.5), rng.uniform(-0.6, 0.6), rng.uniform(0.5, 1.0))
    ground = (ROAD_START, -1.0e4, 0.0)  # with open_sky only the floor's z (the road) is used
    return make_scene(ground, (end, 1.0e4, 1.0e4), [0] * 6, (centres, halves, np.array(yaws), mats), (np.reshape(spheres, (-1, 3)), radii, sphere_mats), (base, accent, freq, kind), sun, 0.5, 0.5,
                      open_sky=True, sky=((0.78, 0.84, 0.9), (0.35, 0.55, 0.85)), device=device)
