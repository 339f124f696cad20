"""Sweep stereo (kernels/stereo.py through mcgs_warp.frontend.stereo) against ray-cast depth,
for every camera model as the reference view, without rectification."""

import numpy as np
import pytest

from mcgs_warp.data.synthetic import SceneRenderer, build_scene
from mcgs_warp.frontend.stereo import RigStereo, StereoConfig, upsample_nearest
from mcgs_warp.geometry import pose, yaw_pitch_roll
from mcgs_warp.rig import CameraSpec, Rig

# OpenCV optical frame (x right, y down, z forward) looking along body +x (world x forward, z up).
Q_FORWARD = (-0.5, 0.5, -0.5, 0.5)

MODELS = {
    "pinhole": ("pinhole", 320, 240, (180.0, 180.0, 159.5, 119.5), (-0.05, 0.01, 0.001, -0.001, 0.0)),
    "fisheye": ("fisheye", 320, 240, (120.0, 120.0, 159.5, 119.5), (0.02, -0.01, 0.0, 0.0)),
    "equirectangular": ("equirectangular", 1024, 512, None, ()),  # 0.35 deg per pixel
}


def two_camera_rig(model: str, baseline: float = 0.3) -> Rig:
    """Reference camera of ``model`` and a pinhole ``baseline`` m to its left, both facing forward."""
    m, w, h, K, dist = MODELS[model]
    ref = CameraSpec("ref", m, w, h, K, dist, pose((0.2, 0.0, 0.0), Q_FORWARD))
    src = CameraSpec("src", "pinhole", 320, 240, (160.0, 160.0, 159.5, 119.5), (), pose((0.2, baseline, 0.0), Q_FORWARD))
    return Rig([ref, src])


def render(rig, T_w_b):
    r = SceneRenderer(build_scene(3), rig, supersample=2)
    color, depth = r.render(T_w_b)
    return [color[i, : c.height, : c.width] for i, c in enumerate(rig.cameras)], [depth[i, : c.height, : c.width] for i, c in enumerate(rig.cameras)]


@pytest.mark.parametrize("model", list(MODELS))
def test_sweep_matches_raycast_depth_for_each_camera_model(model):
    rig = two_camera_rig(model, baseline=0.4)
    T_w_b = np.eye(4)
    T_w_b[:3, :3] = yaw_pitch_roll(0.9)  # towards the left wall: depths of 2-8 m
    T_w_b[:3, 3] = (4.0, 0.3, 1.4)
    images, depths = render(rig, T_w_b)
    stereo = RigStereo(rig, np.ones((2, 2)), StereoConfig(far=60.0))
    assert stereo.pairs == [(0, 1), (1, 0)]
    est, conf = stereo.depth(0, images)
    d, gt = est[0], depths[0]
    ok = (conf[0] > 0) & (gt > 0)
    rel = np.abs(d[ok] - gt[ok]) / gt[ok]
    # The source sees only part of a fisheye's / equirectangular view: judge coverage
    # inside what it can see.
    assert ok.mean() > {"pinhole": 0.25, "fisheye": 0.05, "equirectangular": 0.02}[model], ok.mean()
    assert np.median(rel) <= 0.03, np.median(rel)
    assert (rel > 0.2).mean() < 0.08, (rel > 0.2).mean()


def test_textureless_views_give_no_confident_depth():
    rig = two_camera_rig("pinhole")
    flat = [np.full((c.height, c.width, 3), 0.5, np.float32) for c in rig.cameras]
    _, conf = RigStereo(rig, np.ones((2, 2))).depth(0, flat)
    assert conf[0].max() == 0.0 and conf[1].max() == 0.0


def test_left_right_check_removes_mismatches():
    """Without the check some confident pixels are wrong (occlusions, repetitive texture);
    with it the share of gross errors (off by half the depth) among them falls."""
    rig = two_camera_rig("pinhole", baseline=0.4)
    T_w_b = np.eye(4)
    T_w_b[:3, :3] = yaw_pitch_roll(0.5)
    T_w_b[:3, 3] = (6.0, -0.5, 1.4)
    images, depths = render(rig, T_w_b)

    def gross(lr_px):
        est, conf = RigStereo(rig, np.ones((2, 2)), StereoConfig(lr_px=lr_px)).depth(0, images)
        ok = (conf[0] > 0) & (depths[0] > 0)
        return (np.abs(est[0][ok] - depths[0][ok]) > 0.5 * depths[0][ok]).mean()

    checked, unchecked = gross(1.0), gross(1e9)
    assert checked < 0.5 * unchecked, (checked, unchecked)


def test_temporal_sources_measure_the_far_scene_the_rig_baseline_cannot():
    """A 0.1 m rig pair resolves the far end of the room poorly; sweeping the same view
    against the camera 2 m further back (the rig's own travel, at known poses) measures it,
    and the merge keeps, per pixel, the estimate with the most parallax."""
    rig = two_camera_rig("pinhole", baseline=0.1)
    T_w_b = np.eye(4)
    T_w_b[:3, :3] = yaw_pitch_roll(0.15)  # down the room: far pixels at 8-25 m
    T_w_b[:3, 3] = (3.0, 0.0, 1.4)
    T_back = T_w_b.copy()
    T_back[:3, 3] = (1.0, -0.4, 1.4)  # 2 m of travel back, a little to the side
    images, depths = render(rig, T_w_b)
    back, _ = render(rig, T_back)
    stereo = RigStereo(rig, np.ones((2, 2)), StereoConfig(far=60.0))
    spec = rig.cameras[0]
    T_src_ref = np.linalg.inv(T_back @ spec.T_b_c) @ (T_w_b @ spec.T_b_c)
    s = stereo.cfg.scale
    rig_d, rig_c = stereo.depth(0, images)
    t_d, t_c = stereo.temporal_depth(0, images, [[(back[0], T_src_ref)], []])
    t_d, t_c = upsample_nearest(t_d[0], spec, s), upsample_nearest(t_c[0], spec, s)
    gt = depths[0]

    far = gt > 8.0

    def error(d, c, mask):
        ok = (c > 0) & mask
        return np.median(np.abs(d[ok] - gt[ok]) / gt[ok]), ok.sum()

    rig_err, rig_n = error(rig_d[0], rig_c[0], far)
    t_err, t_n = error(t_d, t_c, far)
    assert t_n >= rig_n, (t_n, rig_n)  # the merge loses no confident far pixel
    assert t_err < 0.8 * rig_err, (t_err, rig_err)
    temporal = t_d != rig_d[0]  # where the temporal sweep won
    won_err, won_n = error(t_d, t_c, far & temporal)
    assert won_n > 0.2 * far.sum() and won_err < 0.1, (won_n, won_err)
    assert error(rig_d[0], rig_c[0], far & temporal & (rig_c[0] > 0))[0] > 1.5 * won_err
