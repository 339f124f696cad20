"""``mcgs-slam view``: a run folder served on a free local port. The page is viser's client,
and a websocket client speaking viser's protocol receives the map as Gaussian splats, one
frustum (with its image) per keyframe view and the two trajectories; the splats' covariances,
colours and opacities are the map's; ground truth moved into the map's frame lands on the
estimate."""

import socket
import urllib.request

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mcgs_warp.data.trajectory import Trajectory, write_tum
from mcgs_warp.errors import InputError
from mcgs_warp.geometry import pose
from mcgs_warp.io import write_image
from mcgs_warp.io.ply import write_ply
from mcgs_warp.rig import CameraSpec, Rig, save_rig
from mcgs_warp.system.outputs import groundtruth_in_map
from mcgs_warp.viewer import GUESSED_COLOUR, load_run, marked_colours, start, stop, vertical_fov

N_GAUSSIANS, N_KEYFRAMES = 200, 4


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    """A run folder as a run leaves it (map.ply, rig.yaml, keyframes.txt, trajectory.txt,
    groundtruth_in_map.txt, images/), with a known map: a world with z up, cameras looking along x."""
    root = tmp_path_factory.mktemp("run")
    rng = np.random.default_rng(0)
    q = Rotation.random(N_GAUSSIANS, random_state=1).as_quat()  # x, y, z, w
    write_ply(root / "map.ply", {"means": rng.uniform(-2, 2, (N_GAUSSIANS, 3)) + [5, 0, 0], "quats": q, "log_scales": rng.uniform(-4, -1, (N_GAUSSIANS, 3)),
                                 "opacity_logits": rng.normal(0, 2, N_GAUSSIANS), "colors": rng.uniform(0, 1, (N_GAUSSIANS, 3)),
                                 "measured": np.arange(N_GAUSSIANS) % 4 != 0})
    R_b_c = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # camera z forward = body x, camera y down = -body z
    rig = Rig([CameraSpec("front", "pinhole", 64, 48, (50.0, 50.0, 32.0, 24.0), T_b_c=pose(np.zeros(3), Rotation.from_matrix(R_b_c).as_quat())),
               CameraSpec("left", "pinhole", 64, 48, (40.0, 40.0, 32.0, 24.0), T_b_c=pose([0, 0.3, 0], Rotation.from_matrix(Rotation.from_euler("z", 90, degrees=True).as_matrix() @ R_b_c).as_quat()))])
    save_rig(rig, root / "rig.yaml")
    t = np.arange(N_KEYFRAMES) * 0.5
    kf = pose(np.column_stack([t, 0.1 * t, np.zeros_like(t)]), np.tile([0, 0, 0, 1.0], (N_KEYFRAMES, 1)))
    write_tum(root / "keyframes.txt", Trajectory(t, kf))
    write_tum(root / "trajectory.txt", Trajectory(t, kf))
    write_tum(root / "groundtruth_in_map.txt", Trajectory(t, kf @ pose([0, 0, 0.01], [0, 0, 0, 1.0])))
    for k in range(N_KEYFRAMES):
        for c in rig.cameras:
            write_image(root / "images" / f"keyframe_{k:03d}_{c.name}.jpg", np.full((48, 64, 3), 0.1 * k, np.float32))
    return root


def test_load_run_gives_the_maps_splats(run_folder):
    from mcgs_warp.io.ply import read_ply

    p = read_ply(run_folder / "map.ply")
    scene = load_run(run_folder)
    assert len(scene.centers) == scene.n_total == N_GAUSSIANS and len(scene.cameras) == 2 * N_KEYFRAMES
    R = Rotation.from_quat(p["quats"]).as_matrix()
    cov = R @ np.einsum("ni,ij->nij", np.exp(2 * p["log_scales"]), np.eye(3)) @ np.swapaxes(R, 1, 2)
    np.testing.assert_allclose(scene.covariances, cov, rtol=1e-4, atol=1e-10)
    np.testing.assert_allclose(scene.opacities[:, 0], 1 / (1 + np.exp(-p["opacity_logits"])), rtol=1e-6)
    np.testing.assert_allclose(scene.rgbs, np.clip(p["colors"], 0, 1), atol=1e-6)
    np.testing.assert_allclose(scene.up, [0, 0, 1], atol=1e-9)  # the cameras' -y: the world's z
    assert scene.cameras[2][0] == "keyframe 1 / front" and scene.cameras[2][4].shape == (48, 64, 3)
    assert vertical_fov(scene.cameras[0][2]) == pytest.approx(2 * np.arctan(24 / 50))
    np.testing.assert_array_equal(scene.measured, p["measured"])
    marked = marked_colours(scene.rgbs, scene.measured, True)
    np.testing.assert_array_equal(marked[scene.measured], scene.rgbs[scene.measured])
    assert (marked[~scene.measured] == GUESSED_COLOUR).all() and (~scene.measured).sum() == N_GAUSSIANS // 4
    np.testing.assert_array_equal(marked_colours(scene.rgbs, scene.measured, False), scene.rgbs)
    few = load_run(run_folder, max_gaussians=10)  # the most opaque ten
    assert len(few.centers) == 10 and few.n_total == N_GAUSSIANS
    assert few.opacities.min() >= np.sort(scene.opacities[:, 0])[-10] - 1e-7


def _scene_messages(port: int, want: int, timeout: float = 20.0) -> list[dict]:
    """Scene messages as viser's browser client receives them (its documented wire format:
    8-byte sizes, a zstd-compressed msgpack of messages, binary buffers after it)."""
    import time

    import msgspec
    import viser
    import zstandard
    from websockets.sync.client import connect

    out = []
    with connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None, open_timeout=10) as ws:
        end = time.time() + timeout
        while time.time() < end and sum(m["type"] == "CameraFrustumMessage" for m in out) < want:
            try:
                data = ws.recv(timeout=max(0.1, end - time.time()))
            except TimeoutError:
                break
            clen = int.from_bytes(data[8:16], "little")
            inner = zstandard.ZstdDecompressor().decompress(data[16 : 16 + clen], max_output_size=int.from_bytes(data[0:8], "little"))
            out.extend(msgspec.msgpack.decode(inner)["messages"])
    return out


def test_view_serves_the_page_and_the_scene(run_folder):
    port = free_port()
    server, handles = start(run_folder, port=port)
    try:
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10).read().decode("utf-8", "replace")
        assert page.lstrip().lower().startswith("<!doctype html>") and "viser" in page.lower()
        msgs = _scene_messages(port, want=2 * N_KEYFRAMES)
        kinds = [m["type"] for m in msgs]
        assert kinds.count("GaussianSplatsMessage") == 1, sorted(set(kinds))
        assert kinds.count("CameraFrustumMessage") == 2 * N_KEYFRAMES
        names = {m["name"] for m in msgs if "name" in m}
        assert {"/map", "/trajectory", "/groundtruth", "/keyframes/keyframe_3_left"} <= names, sorted(names)
        frusta = [m for m in msgs if m["type"] == "CameraFrustumMessage"]
        assert all(m["props"]["_image_data"] is not None for m in frusta)  # each keyframe's image in its frustum
        # looking through a keyframe hides its own frustum (the map shows), and gives it back after
        frusta = dict(handles["frusta"])
        handles["look_through"]("keyframe 2 / left")
        assert not frusta["keyframe 2 / left"].visible and frusta["keyframe 2 / front"].visible
        handles["look_through"]("free camera")
        assert all(f.visible for f in frusta.values())
        # marking the guessed Gaussians sends the map again, the guessed ones magenta (viser's
        # buffer: 32 bytes per splat, the colour in bytes 28-30), and back
        def splat_colours():
            return np.asarray(handles["splats"].buffer).view(np.uint8).reshape(-1, 32)[:, 28:31]

        scene = load_run(run_folder)
        before = splat_colours()
        handles["mark_guessed"](True)
        marked = splat_colours()
        assert (marked[~scene.measured] == [255, 0, 255]).all() and np.array_equal(marked[scene.measured], before[scene.measured])
        assert not np.array_equal(before[~scene.measured], marked[~scene.measured])
        kinds = [m["type"] for m in _scene_messages(port, want=2 * N_KEYFRAMES)]
        assert kinds.count("GaussianSplatsMessage") == 1  # the map replaced, not doubled
        handles["mark_guessed"](False)
        np.testing.assert_array_equal(splat_colours(), before)
        with pytest.raises(InputError, match=f"--port: cannot listen on 127.0.0.1:{port} .*choose another port"):
            start(run_folder, port=port)
    finally:
        stop(server)


def test_view_errors_name_the_file(tmp_path, run_folder):
    with pytest.raises(InputError, match="run folder not found"):
        start(tmp_path / "nothing")
    with pytest.raises(InputError, match="map.ply: missing"):
        start(tmp_path)
    with pytest.raises(InputError, match="--port: expected a port in 1-65535, got 70000"):
        start(run_folder, port=70000)
    with pytest.raises(InputError, match="--host: cannot listen on 10.255.255.1"):  # not this machine's address
        start(run_folder, host="10.255.255.1", port=free_port())


def test_groundtruth_in_map_inverts_the_alignment():
    rng = np.random.default_rng(3)
    t = np.arange(20) * 0.1
    est = Trajectory(t, pose(rng.normal(0, 1, (20, 3)), Rotation.random(20, random_state=2).as_quat()))
    s, R = 1.7, Rotation.from_rotvec([0.2, -0.5, 1.0]).as_matrix()
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = R, [3.0, -1.0, 2.0]
    gt_poses = S @ est.poses
    gt_poses[:, :3, 3] = (est.positions * s) @ R.T + [3.0, -1.0, 2.0]
    back = groundtruth_in_map(est, Trajectory(t, gt_poses), with_scale=True)
    np.testing.assert_allclose(back.poses, est.poses, atol=1e-9)


SCRIPT = __import__("pathlib").Path(__file__).parents[2] / "examples" / "view_screenshot.py"


def test_screenshot_script_says_when_chromium_is_missing(run_folder, tmp_path):
    import os
    import subprocess
    import sys

    env = dict(os.environ, CHROMIUM=str(tmp_path / "no-such-chrome"))
    r = subprocess.run([sys.executable, str(SCRIPT), str(run_folder), "--out", str(tmp_path / "shot.png")], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Chromium not found" in r.stderr and "apt-get install chromium" in r.stderr, r.stderr
    assert not (tmp_path / "shot.png").exists()


def test_screenshot_in_headless_chromium(run_folder, tmp_path):
    """Where Chromium is installed: the browser connects, draws the splats, and the PNG shows them."""
    import subprocess
    import sys

    sys.path.insert(0, str(SCRIPT.parent))
    try:
        from view_screenshot import find_chromium
    finally:
        sys.path.pop(0)
    if find_chromium() is None:
        pytest.skip("Chromium is not installed (apt-get install chromium)")
    out = tmp_path / "shot.png"
    r = subprocess.run([sys.executable, str(SCRIPT), str(run_folder), "--out", str(out), "--size", "480x320"], capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr[-2000:]
    import cv2

    img = cv2.imread(str(out))
    assert img.shape == (320, 480, 3)
    colours = len(np.unique(img.reshape(-1, 3) // 32, axis=0))
    assert colours > 20, colours  # random-coloured splats, not a blank page
