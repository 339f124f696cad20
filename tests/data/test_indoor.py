"""Indoor worlds that vary with the seed (synth --scene indoor): different rooms driven
differently, deterministic, the drive inside the room and clear of every obstacle."""

import numpy as np
import pytest

from mcgs_warp.data.indoor import build_indoor, indoor_layout, indoor_trajectory
from mcgs_warp.data.synthetic import SceneRenderer, synthetic_rig


def test_seeds_draw_different_places_and_drives():
    lays = [indoor_layout(s) for s in range(8)]
    assert indoor_layout(3) == lays[3]
    for key in ("length", "half_width", "height", "speed", "rig_height"):
        values = [getattr(l, key) for l in lays]
        assert np.ptp(values) > 0.2 * np.mean(values), key
    assert any(l.corridor for l in lays) and not all(l.corridor for l in lays)
    assert any(l.pause_start >= 0 for l in lays) and any(l.pause_start < 0 for l in lays)
    a, b = build_indoor(3), build_indoor(3)
    assert np.array_equal(a.box_center.numpy(), b.box_center.numpy()) and np.array_equal(a.mat_base.numpy(), b.mat_base.numpy())


@pytest.mark.parametrize("seed", range(6))
def test_the_drive_stays_in_its_room_clear_of_obstacles(seed):
    lay, n = indoor_layout(seed), 40
    traj = indoor_trajectory(n, seed)
    p = traj.positions
    scene = build_indoor(seed)
    lo, hi = np.array(scene.room_min), np.array(scene.room_max)
    assert np.all(p[:, 0] > lo[0] + 0.5) and np.all(p[:, 0] < hi[0] - 2.5) and np.all(np.abs(p[:, 1]) < hi[1] - 1.0)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert step[0] > 0.5 * lay.speed / 10  # moving from the first frame, not from rest
    if lay.pause_start >= 0:  # standing still: the same pose frame after frame
        still = slice(lay.pause_start, lay.pause_start + lay.pause_frames)
        assert np.allclose(traj.poses[still], traj.poses[lay.pause_start])
    c, h = scene.box_center.numpy(), scene.box_half.numpy()
    clearance = np.abs(c[:, 1]) - np.hypot(h[:, 0], h[:, 1]) - np.abs(p[:, 1]).max()
    assert clearance.min() > 0.4, clearance.min()
    s, r = scene.sphere_center.numpy(), scene.sphere_radius.numpy()
    assert (np.abs(s[:, 1]) - r - np.abs(p[:, 1]).max()).min() > 0.4
    # no camera starts inside or against anything
    _, depth = SceneRenderer(scene, synthetic_rig(3), supersample=1).render(traj.poses[n // 2])
    assert np.all(depth > 0.25) and np.all(depth < np.linalg.norm(hi - lo) + 1), (depth.min(), depth.max())
