"""Camera models: agreement with OpenCV, round trips, and derivatives vs finite differences."""

import cv2
import numpy as np
import pytest

from camera_eval import eval_camera
from warp_devices import devices
from mcgs_warp.kernels import make_camera, reference
from scenes import cameras

MODELS = ["pinhole", "fisheye", "equirectangular"]


def points_in_view(model, n, rng):
    if model == "equirectangular":
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = d[np.abs(d[:, 1]) < 0.95]  # stay away from the poles
    else:
        half = 0.6 if model == "pinhole" else 1.2
        d = np.stack([rng.uniform(-half, half, n), rng.uniform(-half, half, n), np.ones(n)], 1)
    return d * rng.uniform(0.5, 8.0, len(d))[:, None]


@pytest.mark.parametrize("device", devices())
@pytest.mark.parametrize("model", MODELS)
def test_project_matches_reference_and_round_trips(model, device):
    rng = np.random.default_rng(1)
    cam = cameras()[model]
    p = points_in_view(model, 200, rng)
    out = eval_camera(cam, p, np.zeros((len(p), 2, 3)), device)
    np.testing.assert_allclose(out["uv"], reference.project(cam, p), atol=2e-4)
    np.testing.assert_allclose(out["back"], p, rtol=1e-4, atol=1e-4)
    assert out["ok"].all()


def test_pinhole_matches_opencv():
    rng = np.random.default_rng(2)
    cam = cameras()["pinhole"]
    p = points_in_view("pinhole", 300, rng)
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], dtype=np.float64)
    dist = np.array([cam.dist[k] for k in range(5)], dtype=np.float64)
    uv_cv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    np.testing.assert_allclose(reference.project(cam, p), uv_cv.reshape(-1, 2), atol=1e-6)
    out = eval_camera(cam, p, np.zeros((len(p), 2, 3)))
    np.testing.assert_allclose(out["uv"], uv_cv.reshape(-1, 2), atol=1e-4)


def test_fisheye_matches_opencv():
    rng = np.random.default_rng(3)
    cam = cameras()["fisheye"]
    p = points_in_view("fisheye", 300, rng)
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], dtype=np.float64)
    D = np.array([cam.dist[k] for k in range(4)], dtype=np.float64)
    uv_cv, _ = cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    np.testing.assert_allclose(reference.project(cam, p), uv_cv.reshape(-1, 2), atol=1e-6)
    out = eval_camera(cam, p, np.zeros((len(p), 2, 3)))
    np.testing.assert_allclose(out["uv"], uv_cv.reshape(-1, 2), atol=1e-4)


@pytest.mark.parametrize("model", MODELS)
def test_jacobian_and_its_derivative_match_finite_differences(model):
    """J against float64 central differences of the reference projection, and the
    Hessian-vector product ``d<G, J(p)>/dp`` against central differences of J."""
    rng = np.random.default_rng(4)
    cam = cameras()[model]
    p = points_in_view(model, 100, rng)
    p = np.concatenate([p, [[1e-5, -2e-5, 2.0]]]) if model != "equirectangular" else p  # near the axis
    G = rng.normal(size=(len(p), 2, 3))
    out = eval_camera(cam, p, G)
    J_fd = reference.jacobian(cam, p)
    scale = np.abs(J_fd).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(out["J"] / scale, J_fd / scale, atol=2e-5)
    vjp_fd = np.zeros((len(p), 3))
    for k in range(3):
        h = 1e-4 * np.linalg.norm(p, axis=1)
        e = np.zeros(3)
        e[k] = 1
        Jp = reference.jacobian(cam, p + h[:, None] * e, rel_step=1e-5)
        Jm = reference.jacobian(cam, p - h[:, None] * e, rel_step=1e-5)
        vjp_fd[:, k] = ((Jp - Jm) * G).sum(axis=(1, 2)) / (2 * h)
    vscale = np.abs(vjp_fd).max(axis=1, keepdims=True) + 1e-3
    np.testing.assert_allclose(out["vjp"] / vscale, vjp_fd / vscale, atol=2e-3)


def test_domain_rejects_behind_camera_and_folded_distortion():
    cam = make_camera("pinhole", 64, 48, (50, 50, 32, 24), (-0.5, 0.0, 0, 0, 0))
    # r * (1 - 0.5 r^2) stops increasing at r^2 = 2/3: points beyond fold back into the image.
    assert abs(cam.max_r2 - 2.0 / 3.0) < 1e-3
    p = np.array([[0.1, 0.0, 1.0], [0.0, 0.0, -1.0], [0.9, 0.0, 1.0], [0.0, 0.0, 0.005], [0, 0, 200.0]])
    out = eval_camera(cam, p, np.zeros((len(p), 2, 3)))
    assert out["ok"].tolist() == [1, 0, 0, 0, 0]
    np.testing.assert_array_equal(reference.in_domain(cam, p), out["ok"].astype(bool))


@pytest.mark.parametrize(
    "args, message",
    [
        (("kannala", 64, 48, (1, 1, 0, 0)), "camera model"),
        (("pinhole", 0, 48, (1, 1, 0, 0)), "resolution"),
        (("pinhole", 64, 48, (1, 1, 0)), "intrinsics"),
        (("pinhole", 64, 48, (-1, 1, 0, 0)), "intrinsics"),
        (("fisheye", 64, 48, (1, 1, 0, 0), (0, 0, 0, 0, 0)), "distortion"),
        (("pinhole", 64, 48, None), "intrinsics"),
    ],
)
def test_make_camera_rejects_bad_arguments(args, message):
    with pytest.raises(ValueError, match=message):
        make_camera(*args)
