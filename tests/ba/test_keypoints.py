"""Keypoints and multi-camera PnP: a known rig pose recovered from noisy matches with
outliers (pinhole, fisheye and equirectangular cameras together), the LM step's Jacobian
against finite differences, and keypoint depth from the rig's overlapping cameras against
exact depth."""

import numpy as np
import pytest

from mcgs_warp.ba.edges import camera_overlap, unproject_pixels
from mcgs_warp.frontend.keypoints import KeypointDetector, compact_descriptors, masked_matches, mutual_matches, triangulate
from mcgs_warp.frontend.pnp import RigObservations, RigPnP
from mcgs_warp.geometry import pose_distance, se3_exp, yaw_pitch_roll
from mcgs_warp.rig import CameraSpec, Rig
from mcgs_warp.system.config import packaged_config
from mcgs_warp.rig import load_rig


def mixed_rig() -> Rig:
    """The built-in rig (pinhole front, fisheye left, pinhole right, pinhole back) plus an
    equirectangular camera looking up-left."""
    rig = load_rig(packaged_config("rig_synthetic.yaml"))
    T = np.eye(4)
    T[:3, :3] = rig.cameras[0].T_b_c[:3, :3] @ yaw_pitch_roll(0.0, 0.6, 0.0)[:3, :3]
    T[:3, 3] = [0.1, 0.2, 0.3]
    return Rig(rig.cameras + [CameraSpec("pano", "equirectangular", 1024, 512, None, (), T)])


def observations(rig, T_w_b, n_per_camera, noise_px, outliers, rng):
    """Per camera: bearings of random pixels (with pixel noise) and their world points at 2-25 m
    (a share ``outliers`` of them replaced by random points), and which were replaced."""
    obs, replaced = [], []
    for c, spec in enumerate(rig.cameras):
        cam = spec.warp_camera()
        uv = rng.uniform([4, 4], [spec.width - 4, spec.height - 4], size=(n_per_camera, 2))
        rays = unproject_pixels(cam, uv)
        X_c = rays * rng.uniform(2.0, 25.0, size=(n_per_camera, 1))
        T_w_c = T_w_b @ spec.T_b_c
        X_w = X_c @ T_w_c[:3, :3].T + T_w_c[:3, 3]
        noisy = unproject_pixels(cam, uv + rng.normal(0, noise_px, uv.shape))
        b = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)
        bad = rng.random(n_per_camera) < outliers
        X_w[bad] = rng.uniform(-20, 20, size=(bad.sum(), 3))
        obs.append(RigObservations(c, b, X_w))
        replaced.append(bad)
    return obs, replaced


@pytest.mark.parametrize("guess", [None, "far"], ids=["no-guess", "wrong-guess"])
def test_rig_pnp_recovers_a_known_pose(guess):
    rng = np.random.default_rng(3)
    rig = mixed_rig()
    T_true = se3_exp(np.array([3.0, -1.0, 0.4, 0.3, -0.2, 1.2]))
    obs, replaced = observations(rig, T_true, 60, 0.3, 0.4, rng)
    T_guess = None if guess is None else T_true @ se3_exp(np.array([1.5, 0.5, 0.0, 0.0, 0.0, 0.5]))
    res = RigPnP(rig, seed=1).solve(obs, guess=T_guess)
    assert res is not None and not res.from_guess
    dt, dr = pose_distance(res.T_w_b, T_true)
    assert dt < 0.01 and np.degrees(dr) < 0.05, (dt, np.degrees(dr))
    # the consensus finds the inliers of every camera model, and few outliers pass
    for m, bad in zip(res.inliers, replaced):
        assert m[~bad].mean() > 0.8  # 0.3 px of noise is up to 0.002 rad per axis on these cameras
        assert m[bad].mean() < 0.1


def test_rig_pnp_inliers_follow_the_sets_given_even_empty_ones():
    rng = np.random.default_rng(6)
    rig = mixed_rig()
    T_true = se3_exp(np.array([0.5, 0.2, 0.0, 0.0, 0.0, 0.3]))
    obs, _ = observations(rig, T_true, 30, 0.0, 0.0, rng)
    obs[1] = RigObservations(1, np.zeros((0, 3)), np.zeros((0, 3)))
    res = RigPnP(rig).solve(obs)
    assert res is not None and len(res.inliers) == len(obs)
    assert [len(m) for m in res.inliers] == [len(o.bearings) for o in obs] and res.inliers[0].all()


def test_rig_pnp_refuses_noise():
    rng = np.random.default_rng(5)
    rig = mixed_rig()
    T_true = se3_exp(np.array([0.5, 0.2, 0.0, 0.0, 0.0, 0.3]))
    obs, _ = observations(rig, T_true, 30, 0.0, 1.0, rng)  # nothing but outliers
    assert RigPnP(rig, seed=0).solve(obs, min_inliers=20) is None


def test_pnp_linearization_matches_finite_differences():
    rng = np.random.default_rng(7)
    rig = mixed_rig()
    T = se3_exp(np.array([1.0, 0.5, 0.2, 0.1, 0.2, 0.3]))
    o = observations(rig, T @ se3_exp(np.array([0.05, -0.02, 0.03, 0.01, 0.02, -0.01])), 20, 0.0, 0.0, rng)[0][1]  # the fisheye camera
    pnp = RigPnP(rig)
    r, J, _w = pnp._linearize(T, o.camera, o.bearings, o.points_w)
    eps = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        rp = pnp._residual(T @ se3_exp(d), o.camera, o.bearings, o.points_w)[0]
        rm = pnp._residual(T @ se3_exp(-d), o.camera, o.bearings, o.points_w)[0]
        np.testing.assert_allclose(J[:, :, i], (rp - rm) / (2 * eps), atol=1e-6)


def test_triangulation_of_two_rays():
    rng = np.random.default_rng(0)
    T_a_b = se3_exp(np.array([0.5, 0.0, 0.05, 0.0, 0.1, 0.0]))
    X_a = rng.uniform([-3, -2, 4], [3, 2, 20], size=(50, 3))
    X_b = (X_a - T_a_b[:3, 3]) @ T_a_b[:3, :3]
    X, s, r = triangulate(T_a_b, X_a / np.linalg.norm(X_a, axis=1, keepdims=True), X_b / np.linalg.norm(X_b, axis=1, keepdims=True))
    np.testing.assert_allclose(X, X_a, atol=1e-9)
    np.testing.assert_allclose(s, np.linalg.norm(X_a, axis=1), rtol=1e-9)
    np.testing.assert_allclose(r, np.linalg.norm(X_b, axis=1), rtol=1e-9)


def test_mutual_matches_pair_the_same_descriptors():
    rng = np.random.default_rng(2)
    a = rng.random((40, 128)).astype(np.float32)
    perm = rng.permutation(40)
    b = a[perm] + rng.normal(0, 0.01, (40, 128)).astype(np.float32)
    m = mutual_matches(a, b)
    assert len(m) == 40
    np.testing.assert_array_equal(perm[m[:, 1]], m[:, 0])


def test_views_keep_sift_descriptors_as_uint8_and_match_as_before(synthetic_seq):
    """A kept view's descriptors are uint8 (a quarter of the memory every keyframe's views hold) and the
    same values OpenCV's SIFT gave as float32, so matching them gives the same pairs; descriptors
    that are not whole numbers in 0-255 stay float32."""
    import cv2

    from mcgs_warp.frontend.keypoints import to_grey8

    rig = synthetic_seq.rig
    frame = synthetic_seq[0]
    views = KeypointDetector(rig, []).detect(frame.images)
    assert all(v.desc.dtype == np.uint8 and v.desc.shape == (len(v), 128) for v in views)
    sift = cv2.SIFT_create(nfeatures=1000, contrastThreshold=0.02)
    _, raw = sift.detectAndCompute(to_grey8(frame.images[0]), None)
    assert raw.dtype == np.float32 and len(raw) == len(views[0]) >= 50
    np.testing.assert_array_equal(views[0].desc.astype(np.float32), raw)
    a, b = views[0].desc, views[1].desc
    np.testing.assert_array_equal(mutual_matches(a, b), mutual_matches(a.astype(np.float32), b.astype(np.float32)))
    band = np.random.default_rng(0).random((len(a), len(b))) < 0.3
    m = masked_matches(a, b, band)  # squares of uint8 would wrap: the matcher must take floats
    np.testing.assert_array_equal(m, masked_matches(a.astype(np.float32), b.astype(np.float32), band))
    assert len(m) > 0
    frac = raw * 0.5 + 0.25
    assert compact_descriptors(frac).dtype == np.float32 and np.array_equal(compact_descriptors(frac), frac)
    assert compact_descriptors(raw + 256.0).dtype == np.float32  # whole numbers beyond 255
    assert compact_descriptors(None).shape == (0, 128)


def test_rig_stereo_keypoint_depth_matches_exact_depth(synthetic_seq):
    """Keypoints of the built-in rig's overlapping cameras triangulated without any depth:
    their depth agrees with the exact depth at the keypoint (within what half a pixel of
    disparity allows)."""
    rig = synthetic_seq.rig
    overlap = camera_overlap(rig, stride=8)
    pairs = [(a, b) for a in range(len(rig)) for b in range(len(rig)) if a < b and overlap[a, b] > 0.05 and overlap[b, a] > 0.05]
    assert pairs
    det = KeypointDetector(rig, pairs)
    frame = synthetic_seq[0]
    views = det.detect(frame.images)
    n, errs = 0, []
    for c, v in enumerate(views):
        gt = frame.depths[c]
        has = v.has_depth
        n += has.sum()
        ui, vi = np.rint(v.uv[has]).astype(int).T
        z_true = gt[vi, ui]
        z = v.points[has, 2] if rig.cameras[c].model != "equirectangular" else np.linalg.norm(v.points[has], axis=1)
        ok = z_true > 0
        errs.append(np.abs(z[ok] - z_true[ok]) / z_true[ok])
    errs = np.concatenate(errs)
    assert n >= 20
    # 0.2-0.3 m baselines at 2-8 m on 320 px views: about 10 px of disparity, so half a pixel is 5 %
    assert np.median(errs) < 0.08, np.median(errs)
    assert np.percentile(errs, 25) < 0.04


def test_triangulate_takes_one_pose_per_pair():
    """A pose per pair [P,4,4] (rig_motion's pairs of different cameras) gives what each pair's
    own pose gives."""
    rng = np.random.default_rng(2)
    T = se3_exp(rng.normal(0, 0.5, (5, 6)))
    a = rng.normal(size=(5, 3)) + [0, 0, 4]
    b = rng.normal(size=(5, 3)) + [0, 0, 4]
    X, s, r = triangulate(T, a, b)
    for p in range(5):
        Xp, sp, rp = triangulate(T[p], a[p : p + 1], b[p : p + 1])
        np.testing.assert_allclose(X[p], Xp[0], atol=1e-12)
        np.testing.assert_allclose([s[p], r[p]], [sp[0], rp[0]], atol=1e-12)
