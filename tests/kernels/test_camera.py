"""Camera models: agreement with OpenCV, round trips, and derivatives vs finite differences."""

import cv2
import numpy as np
import pytest

from camera_eval import eval_camera
from warp_devices import devices
from mcgs_warp.kernels import make_camera, reference
from mcgs_warp.kernels.sweep import camera_rays
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


def has_ray_reference(cam, uv):
    """float64: does pixel ``uv`` [M,2] of a radial-only pinhole or fisheye camera have a
    ray in the model's domain? Its normalized radius must be reached by the monotonic part
    of the distortion curve (pinhole: |n|^2 <= max_r2; fisheye: angles below 90 degrees)."""
    k = np.array([cam.dist[i] for i in range(5)], np.float64)
    r_d = np.hypot((uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy)
    if cam.model == 1:  # fisheye: theta_d(theta), theta < 90 degrees
        t = np.linspace(0.0, np.pi / 2, 200001)[:-1]
        curve = t * (1 + k[0] * t**2 + k[1] * t**4 + k[2] * t**6 + k[3] * t**8)
    else:
        r = np.sqrt(np.linspace(0.0, cam.max_r2, 200001))
        curve = r * (1 + k[0] * r**2 + k[1] * r**4 + k[4] * r**6)
    return r_d <= curve.max()


@pytest.mark.parametrize("device", devices())
@pytest.mark.parametrize(
    "model, size, intrinsics, dist, no_ray",
    [
        # TUM-VI-like fisheye (195 degrees): the image corners lie beyond 90 degrees off the axis
        ("fisheye", (128, 128), (48.0, 48.0, 63.7, 64.2), (0.0034, 0.0007, -0.0017, 0.0003), (0.04, 0.10)),
        # strong barrel distortion: most pixels are reached only past the fold of r (1 + k1 r^2)
        ("pinhole", (160, 120), (62.5, 62.5, 80.0, 60.0), (-0.35, 0.0, 0.0, 0.0, 0.0), (0.5, 0.9)),
    ],
)
def test_pixels_without_a_ray_unproject_to_nan(model, size, intrinsics, dist, no_ray, device):
    """camera_unproject gives NaN exactly where the model has no ray (up to pixels next to
    the boundary), and every ray it gives projects back onto its pixel; camera_in_domain
    rejects the NaN point, so no consumer can match or optimise it."""
    cam = make_camera(model, *size, intrinsics, dist)
    v, u = np.mgrid[0 : size[1], 0 : size[0]]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    rays = camera_rays(cam, device).numpy().reshape(-1, 3)
    finite = np.isfinite(rays).all(1)
    assert (np.isnan(rays[~finite])).all()  # NaN in all three coordinates, never inf
    ref = has_ray_reference(cam, uv)
    assert no_ray[0] < 1 - ref.mean() < no_ray[1]
    r_d = np.hypot((uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy)
    edge = np.abs(r_d - r_d[ref].max()) < 1.0 / cam.fx  # within a pixel of the boundary
    assert (finite[~edge] == ref[~edge]).all(), (finite != ref).sum()
    n2 = (rays[finite, :2] ** 2).sum(1)
    assert (n2 <= np.float32(cam.max_r2)).all()
    np.testing.assert_allclose(reference.project(cam, rays[finite]), uv[finite], atol=0.01)
    p = np.concatenate([rays[~finite][:3] * 2.0, rays[finite][:1] * 2.0])
    out = eval_camera(cam, p, np.zeros((len(p), 2, 3)), device)
    assert out["ok"].tolist() == [0, 0, 0, 1]
    assert not reference.in_domain(cam, p[:3]).any()


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


@pytest.mark.parametrize("model", MODELS)
def test_host_point_projection_matches_reference(model):
    """project_points (the host side's camera: the kernels' model, not the float64 test
    reference) gives the reference's pixels and Jacobians where the reference says the point
    is in the domain, and rejects points behind, beyond the far plane and non-finite ones."""
    from mcgs_warp.ba.edges import project_points

    rng = np.random.default_rng(4)
    cam = cameras()[model]
    p = points_in_view(model, 300, rng)
    bad = np.array([[0.0, 0.0, -2.0], [0.1, 0.2, 1e6], [np.nan, 0.0, 3.0], [0.0, np.inf, 1.0]])
    if model == "equirectangular":
        bad = bad[1:]  # a sphere sees behind it
    uv, ok, J = project_points(cam, np.concatenate([p, bad]).reshape(-1, 1, 3), jacobian=True)
    assert uv.shape == (len(p) + len(bad), 1, 2) and ok.shape == (len(p) + len(bad), 1) and J.shape == (len(p) + len(bad), 1, 2, 3)
    uv, ok, J = uv[:, 0], ok[:, 0], J[:, 0]
    assert ok[: len(p)].all() and not ok[len(p) :].any()
    assert (uv[len(p) :] == 0).all()
    np.testing.assert_allclose(uv[: len(p)], reference.project(cam, p), atol=2e-4)
    np.testing.assert_allclose(J[: len(p)], reference.jacobian(cam, p), rtol=2e-3, atol=2e-3)
    _, ok_near, _ = project_points(cam, p, near=float(np.linalg.norm(p, axis=1).max()) + 1.0)
    assert not ok_near.any()


@pytest.mark.parametrize("model", MODELS)
def test_float64_host_model_matches_reference_and_kernels(model):
    """ba.camera64 (the solvers' float64 camera with analytic Jacobians) gives the float64
    reference's pixels to 1e-9 px, its central-difference Jacobians, the kernels' pixels, and
    the same domain: behind the camera, beyond the far plane, past a pinhole's monotonic
    distortion radius and non-finite points do not project."""
    from mcgs_warp.ba.camera64 import project
    from mcgs_warp.ba.edges import project_points

    rng = np.random.default_rng(7)
    cam = cameras()[model]
    p = points_in_view(model, 300, rng)
    uv, ok, J = project(cam, p, jacobian=True)
    assert ok.all()
    np.testing.assert_allclose(uv, reference.project(cam, p), atol=1e-9)
    np.testing.assert_allclose(J, reference.jacobian(cam, p), rtol=1e-5, atol=1e-5 * np.abs(J).max())
    np.testing.assert_allclose(uv, project_points(cam, p)[0], atol=2e-4)
    bad = np.array([[0.1, 0.2, 1e6], [np.nan, 0.0, 3.0], [0.0, np.inf, 1.0]] + ([] if model == "equirectangular" else [[0.0, 0.0, -2.0]]) + ([[50.0, 0.0, 1.0]] if model == "pinhole" else []))  # the last: past the distortion's monotonic radius
    uv_b, ok_b, J_b = project(cam, bad, jacobian=True)
    assert not ok_b.any() and (uv_b == 0).all() and (J_b == 0).all()
    assert (ok_b == project_points(cam, bad)[1]).all()
