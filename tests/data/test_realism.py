"""Sensor realism (synth --realism camera) against closed-form values: the blur length from
the motion, the gains, the noise level; deterministic for a seed."""

import numpy as np
import pytest

from mcgs_warp.data.realism import CameraRealism, add_noise, image_motion, motion_blur, vignetting
from mcgs_warp.rig import CameraSpec

F, W, H = 200.0, 64, 48


def pinhole():
    return CameraSpec("c", "pinhole", W, H, (F, F, (W - 1) / 2, (H - 1) / 2))


def unit_rays(spec):
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    fx, fy, cx, cy = spec.intrinsics
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)


def test_image_motion_of_a_plane_and_of_the_sky():
    """A fronto-parallel plane at Z = 4 m while the camera moves 0.1 m to the right: every
    point moves f t / Z = 5 px to the left. The sky (no depth) under a pure pan of a moves by
    the rotation alone: f tan(a) at the centre."""
    spec = pinhole()
    cam = spec.warp_camera()
    T = np.eye(4)
    T[0, 3] = -0.1  # frame-0 camera coordinates -> frame 1: the camera moved +0.1 m along x
    d = image_motion(unit_rays(spec), np.full((H, W), 4.0), cam, T)
    np.testing.assert_allclose(d[..., 0], -F * 0.1 / 4.0, atol=1e-4)
    np.testing.assert_allclose(d[..., 1], 0.0, atol=1e-4)
    a = 0.01
    R = np.eye(4)
    R[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    d = image_motion(unit_rays(spec), np.zeros((H, W)), cam, R)
    assert d[H // 2, W // 2, 0] == pytest.approx(F * np.tan(a), rel=1e-3)  # no translation can move the sky


def test_motion_blur_is_a_box_of_the_motion_length():
    """A vertical step edge blurred along x by a 6 px motion becomes a 6 px linear ramp:
    0.5 at the edge, 0.25 / 0.75 at 1.5 px either side, untouched beyond 3 px."""
    img = np.zeros((H, W, 3), np.float32)
    img[:, W // 2 :] = 1.0
    out = motion_blur(img, np.tile(np.float32([6.0, 0.0]), (H, W, 1)), samples=60)
    row = out[H // 2, :, 0]
    edge = W // 2 - 0.5  # between the last dark and the first bright pixel
    x = np.arange(W)
    np.testing.assert_allclose(row, np.clip((x - edge) / 6.0 + 0.5, 0, 1), atol=0.02)
    assert np.array_equal(out[:, : W // 2 - 4], img[:, : W // 2 - 4])


def test_noise_level_follows_shot_and_read_noise():
    cfg = CameraRealism()
    rng = np.random.default_rng(0)
    for level in (0.1, 0.5):
        noisy = add_noise(np.full((200, 200, 3), level, np.float32), cfg, rng)
        assert noisy.std() == pytest.approx(np.sqrt(cfg.shot * level + cfg.read**2), rel=0.03)
        assert abs(noisy.mean() - level) < 1e-3


def test_vignetting_darkens_the_corners_only():
    v = vignetting(pinhole(), 0.3)
    assert v[H // 2, W // 2] > 0.999 and v[0, 0] == pytest.approx(1 - 0.3 * ((W - 1) ** 2 + (H - 1) ** 2) / (W * W + H * H), rel=1e-6)


def test_synth_with_camera_realism(tmp_path):
    """The recorded image is the clean render times the frame's gain (gt/gains.txt) near the
    image centre (no vignetting there), plus noise; the same seed writes the same files."""
    import cv2

    from mcgs_warp.data.synthetic import generate

    clean = generate(tmp_path / "clean", n_cameras=2, n_frames=3, seed=5, progress=False)
    real = generate(tmp_path / "real", n_cameras=2, n_frames=3, seed=5, progress=False, realism="camera")
    generate(tmp_path / "again", n_cameras=2, n_frames=3, seed=5, progress=False, realism="camera")
    gains = np.loadtxt(tmp_path / "real" / "gt" / "gains.txt")
    assert gains.shape == (3, 2) and np.all(np.abs(np.log(gains)) <= 0.3 + 1e-9) and gains.std() > 0.01
    for k in range(3):
        for c in range(2):
            a, b = clean[k].images[c], real[k].images[c]
            centre = (slice(100, 140), slice(140, 180))
            mid = (a[centre] > 0.1) & (a[centre] * gains[k, c] < 0.9)
            ratio = np.median(b[centre][mid] / a[centre][mid])
            assert ratio == pytest.approx(gains[k, c], rel=0.03), (k, c, ratio, gains[k, c])
            assert 0.005 < np.abs(b - np.clip(a * gains[k, c], 0, 1))[centre].mean() < 0.05  # noise and JPEG are there
            assert np.array_equal(cv2.imread(str(tmp_path / "real" / f"cam{c}" / "rgb" / f"{k:06d}.png")), cv2.imread(str(tmp_path / "again" / f"cam{c}" / "rgb" / f"{k:06d}.png")))
    np.testing.assert_array_equal(real.gt_depths(1)[0], clean.gt_depths(1)[0])  # geometry unchanged
