"""The street scene (synth --scene street) against closed forms: the road's depth, the sky,
the depth range and layout a seed draws."""

import numpy as np
import pytest

from mcgs_warp.data.street import CAMERA_HEIGHT, LANE, ROAD_END, SPEED, build_street, road_end, street_trajectory
from mcgs_warp.data.synthetic import SceneRenderer
from mcgs_warp.rig import CameraSpec, Rig

F = 180.0


def level_camera(pitch_deg: float = 0.0) -> Rig:
    """One undistorted pinhole at the body origin looking along +x, pitched up by ``pitch_deg``."""
    from mcgs_warp.geometry import yaw_pitch_roll

    T = np.eye(4)
    T[:3, :3] = yaw_pitch_roll(0.0, -np.radians(pitch_deg), 0.0) @ np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return Rig([CameraSpec("c", "pinhole", 320, 240, (F, F, 159.5, 119.5), (), T)])


def body_at(x: float, y: float = -LANE) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, CAMERA_HEIGHT]
    return T


def test_the_road_ahead_is_a_plane_at_camera_height():
    """Straight down the empty lane, a pixel v rows below the horizon sees the road at depth
    h f / v (h = 1.6 m): 7.2 m at 40 rows, 28.8 m at 10 rows."""
    colour, depth = SceneRenderer(build_street(0), level_camera()).render(body_at(0.0))
    for rows in (40, 10):
        assert depth[0, 119 + rows, 159] == pytest.approx(CAMERA_HEIGHT * F / (rows - 0.5), rel=1e-4)  # centre rows at 119.5


def test_the_sky_has_no_depth_and_its_own_colour():
    colour, depth = SceneRenderer(build_street(0), level_camera(pitch_deg=60.0)).render(body_at(0.0))
    sky = depth[0] == 0
    assert sky[:40].mean() > 0.9  # looking 60 degrees up between the façades
    c = colour[0][sky]
    assert np.all(c[:, 2] > c[:, 0]) and np.all(c <= 0.95) and np.median(c[:, 0]) > 0.3  # blue, between zenith and horizon


def test_depth_from_a_few_metres_to_beyond_100_m_and_the_drive():
    """The built-in street rig along the drive: parked cars about a metre from a side camera,
    the road and façades beyond 100 m; 10 m/s in the right lane."""
    from mcgs_warp.data.synthetic import synthetic_rig

    traj = street_trajectory(30, 10.0, seed=1)
    np.testing.assert_allclose(np.linalg.norm(np.diff(traj.positions[:, :2], axis=0), axis=1) * 10.0, SPEED, rtol=0.01)
    assert np.all(np.abs(traj.positions[:, 1] + LANE) <= 0.3) and np.allclose(traj.positions[:, 2], CAMERA_HEIGHT)
    r = SceneRenderer(build_street(1), synthetic_rig(3, "rig_street.yaml"))
    seen = np.concatenate([r.render(traj.poses[k])[1].ravel() for k in (0, 15, 29)])
    hit = seen[seen > 0]
    assert 0.8 < hit.min() < 3.0 and hit.max() > 100.0 and np.mean(hit > 30.0) > 0.01 and np.mean(seen == 0) > 0.01


def test_layout_is_deterministic_and_drawn_from_the_seed():
    a, b, c = build_street(3), build_street(3), build_street(4)
    assert np.array_equal(a.box_center.numpy(), b.box_center.numpy()) and np.array_equal(a.sphere_radius.numpy(), b.sphere_radius.numpy())
    assert a.box_center.shape != c.box_center.shape or not np.allclose(a.box_center.numpy(), c.box_center.numpy())
    # nothing stands in the rig's lane (|y + LANE| < 1.1 m: the rig, its cameras, a margin)
    centre, half = a.box_center.numpy(), a.box_half.numpy()
    lane = (np.abs(centre[:, 1] + LANE) - np.abs(half[:, 1]) < 1.1) & (centre[:, 2] - half[:, 2] < 2.5) & (centre[:, 0] < 250)
    assert not lane[np.abs(half[:, 0]) < 50].any()  # (the long kerbs and the far block excepted)


def test_a_long_drive_gets_a_longer_road_and_a_short_one_keeps_its_layout():
    """A 300-frame drive (300 m) would pass the standard road's end (260 m): its road goes on
    beyond its last pose, façades included; drives that fit keep the standard road, so what a
    seed gave the benchmark worlds stays."""
    assert road_end(40) == road_end(220) == ROAD_END
    end = road_end(300)
    last = street_trajectory(300, 10.0, seed=0).positions[-1, 0]
    assert end >= last + 40.0
    np.testing.assert_array_equal(build_street(2).box_center.numpy(), build_street(2, end=road_end(200)).box_center.numpy())
    long = build_street(2, end=end)
    centre, half = long.box_center.numpy(), long.box_half.numpy()
    facades = (np.abs(centre[:, 1]) > 8.0) & (np.abs(half[:, 0]) < 20.0)
    assert centre[facades, 0].max() > last  # buildings beside the drive's end
    assert centre[:, 0].max() > end  # the block across the far end, beyond it
