"""``mcgs-slam view RUN``: a run folder in the browser, through viser.

viser (the web viewer nerfstudio is built on) serves a three.js client from a local port
and draws Gaussian splats natively; it needs no display or GPU on the machine that runs
it, so a run on a server is viewed through SSH port forwarding. What is shown:

* the map's Gaussians (``map.ply``) as splats: means, covariances ``R diag(s^2) R^T``,
  colours, opacities; the most opaque ``max_gaussians`` where the map holds more;
* each keyframe camera (``keyframes.txt`` x ``rig.yaml``) as a frustum holding its input image
  (``images/``), coloured per rig camera; clicking one, or choosing it in the panel, looks
  through it (the camera's pose and vertical field of view; its own frustum hidden, so the
  map's render shows where the image was);
* the rig's trajectory (``trajectory.txt``, orange) and the ground truth in the map's frame
  (``groundtruth_in_map.txt``, green) where the run had one.

Up is the mean of the keyframe cameras' up direction (-y of the OpenCV camera frame), so
maps whose world is a camera frame (KITTI) stand upright.
"""

from __future__ import annotations

import contextlib
import io
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .geometry import quat_to_matrix

CAMERA_COLOURS = [(230, 80, 60), (60, 140, 230), (80, 190, 90), (200, 160, 40), (160, 90, 200), (40, 190, 190)]
TRAJECTORY_COLOUR, GROUNDTRUTH_COLOUR = (255, 140, 0), (40, 200, 80)
FREE = "free camera"


@dataclass
class RunScene:
    """What a run folder holds for the viewer (arrays in the map's world frame, metres)."""

    centers: np.ndarray  # [N,3]
    covariances: np.ndarray  # [N,3,3]
    rgbs: np.ndarray  # [N,3] in [0,1]
    opacities: np.ndarray  # [N,1] in [0,1]
    cameras: list = field(default_factory=list)  # (label, T_w_c [4,4], CameraSpec, camera index, image [H,W,3] uint8 or None)
    trajectory: np.ndarray | None = None  # [K,3] rig positions
    groundtruth: np.ndarray | None = None  # [M,3]
    n_total: int = 0  # Gaussians in the map before max_gaussians
    measured: np.ndarray | None = None  # [N] bool: placed at a measured depth (None: the PLY does not say)

    @property
    def up(self) -> np.ndarray:
        if not self.cameras:
            return np.array([0.0, 0.0, 1.0])
        u = -np.mean([T[:3, 1] for _, T, *_ in self.cameras], axis=0)
        return u / max(np.linalg.norm(u), 1e-12)


def load_run(run, max_gaussians: int = 500_000) -> RunScene:
    """Read a run folder's map, keyframe cameras and trajectories (errors name the file)."""
    import cv2

    from .data.trajectory import read_tum
    from .io.ply import read_ply
    from .rig import load_rig

    run = Path(run)
    if not run.is_dir():
        raise InputError(run, None, "run folder not found")
    if not (run / "map.ply").is_file():
        raise InputError(run / "map.ply", None, "missing: not a finished run folder (a run writes map.ply at its end)")
    p = read_ply(run / "map.ply")
    opacity = 1.0 / (1.0 + np.exp(-p["opacity_logits"].astype(np.float64)))
    keep = np.argsort(-opacity)[:max_gaussians] if len(opacity) > max_gaussians else np.arange(len(opacity))
    R = quat_to_matrix(p["quats"][keep])
    s2 = np.exp(2.0 * p["log_scales"][keep].astype(np.float64))
    cov = (R * s2[:, None, :]) @ np.swapaxes(R, 1, 2)
    scene = RunScene(p["means"][keep].astype(np.float32), cov.astype(np.float32), np.clip(p["colors"][keep], 0, 1).astype(np.float32),
                     opacity[keep, None].astype(np.float32), n_total=len(opacity), measured=None if p["measured"] is None else p["measured"][keep])
    if (run / "rig.yaml").is_file() and (run / "keyframes.txt").is_file():
        rig, kfs = load_rig(run / "rig.yaml"), read_tum(run / "keyframes.txt")
        for k, T in enumerate(kfs.poses):
            for c, spec in enumerate(rig.cameras):
                img_path = run / "images" / f"keyframe_{k:03d}_{spec.name}.jpg"
                img = cv2.imread(str(img_path), cv2.IMREAD_COLOR) if img_path.is_file() else None
                scene.cameras.append((f"keyframe {k} / {spec.name}", T @ spec.T_b_c, spec, c, None if img is None else img[..., ::-1].copy()))
    if (run / "trajectory.txt").is_file():
        scene.trajectory = read_tum(run / "trajectory.txt").positions
    if (run / "groundtruth_in_map.txt").is_file():
        scene.groundtruth = read_tum(run / "groundtruth_in_map.txt").positions
    return scene


def vertical_fov(spec) -> float:
    """Vertical field of view (rad) of a camera: 2 atan(h / 2 fy) for pinhole and fisheye
    (the undistorted pinhole equivalent), pi for equirectangular."""
    if spec.model == "equirectangular" or spec.intrinsics is None:
        return float(np.pi * 0.9)
    return float(2.0 * np.arctan2(spec.height / 2.0, spec.intrinsics[1]))


def _wxyz(T: np.ndarray) -> np.ndarray:
    from .geometry import matrix_to_quat

    x, y, z, w = matrix_to_quat(T[:3, :3])
    return np.array([w, x, y, z])


def _polyline(points: np.ndarray) -> np.ndarray:
    return np.stack([points[:-1], points[1:]], axis=1).astype(np.float32)


GUESSED_COLOUR = (1.0, 0.0, 1.0)  # magenta: Gaussians placed at a guessed depth, when the viewer marks them


def marked_colours(rgbs: np.ndarray, measured: np.ndarray | None, mark: bool) -> np.ndarray:
    """The splats' colours [N,3]; with ``mark`` the guessed ones (``~measured``) in
    :data:`GUESSED_COLOUR`, so a user sees which depth nothing measured."""
    if not mark or measured is None:
        return rgbs
    return np.where(np.asarray(measured, bool)[:, None], rgbs, np.asarray(GUESSED_COLOUR, rgbs.dtype))


def build_scene(server, scene: RunScene) -> dict:
    """Add the run's scene and the panel to a viser server; returns the handles by kind."""
    handles: dict = {"splats": None, "frusta": [], "lines": []}
    server.scene.set_up_direction(tuple(float(v) for v in scene.up))
    if len(scene.centers):
        handles["splats"] = server.scene.add_gaussian_splats("/map", scene.centers, scene.covariances, scene.rgbs, scene.opacities)
    extent = float(np.ptp(scene.trajectory, axis=0).max()) if scene.trajectory is not None and len(scene.trajectory) > 1 else 1.0
    size = float(np.clip(0.03 * extent, 0.05, 2.0))
    for label, T, spec, c, img in scene.cameras:
        f = server.scene.add_camera_frustum(f"/keyframes/{label.replace(' / ', '_').replace(' ', '_')}", fov=vertical_fov(spec), aspect=spec.width / spec.height,
                                            scale=size, thickness=0.04 * size, color=CAMERA_COLOURS[c % len(CAMERA_COLOURS)], image=img, format="jpeg",
                                            wxyz=_wxyz(T), position=T[:3, 3])
        handles["frusta"].append((label, f))
    for name, pts, colour in (("/trajectory", scene.trajectory, TRAJECTORY_COLOUR), ("/groundtruth", scene.groundtruth, GROUNDTRUTH_COLOUR)):
        if pts is not None and len(pts) > 1:
            handles["lines"].append(server.scene.add_line_segments(name, _polyline(pts), colour, thickness=0.1 * size))
    views = {label: (T, spec) for label, T, spec, _, _ in scene.cameras}

    hidden: list = []  # the frustum of the view looked through: hidden, so the map shows, not its image

    def look_through(label: str, clients=None) -> None:
        frusta = dict(handles["frusta"])
        for f in hidden:
            f.visible = show_frusta.value
        hidden.clear()
        if label not in views:
            return
        frusta[label].visible = False
        hidden.append(frusta[label])
        T, spec = views[label]
        for client in (clients or server.get_clients().values()):
            with client.atomic():
                client.camera.wxyz = _wxyz(T)
                client.camera.position = T[:3, 3]
                client.camera.fov = vertical_fov(spec)

    with server.gui.add_folder("Run"):
        server.gui.add_markdown(f"{scene.n_total} Gaussians" + (f" (the {len(scene.centers)} most opaque shown)" if scene.n_total > len(scene.centers) else "")
                                + f", {len(scene.cameras)} keyframe views")
        choose = server.gui.add_dropdown("Look through", options=[FREE] + list(views), initial_value=FREE)
        choose.on_update(lambda event: look_through(choose.value, [event.client] if event.client is not None else None))
        show_frusta = server.gui.add_checkbox("Keyframe cameras", True)
        show_lines = server.gui.add_checkbox("Trajectories", True)
        if scene.measured is not None and len(scene.centers):
            mark = server.gui.add_checkbox(f"Guessed depth in magenta ({100 * (1 - scene.measured.mean()):.0f} % of the Gaussians)", False)

            def mark_guessed(on: bool) -> None:
                handles["splats"].remove()
                handles["splats"] = server.scene.add_gaussian_splats("/map", scene.centers, scene.covariances, marked_colours(scene.rgbs, scene.measured, on), scene.opacities)

            mark.on_update(lambda _: mark_guessed(mark.value))
            handles["mark_guessed"] = mark_guessed

    def toggle(_):
        for _, f in handles["frusta"]:
            f.visible = show_frusta.value
        for line in handles["lines"]:
            line.visible = show_lines.value

    show_frusta.on_update(toggle)
    show_lines.on_update(toggle)
    for label, f in handles["frusta"]:
        f.on_click(lambda event, label=label: look_through(label, [event.client]))
    handles["look_through"] = look_through
    return handles


def start(run, host: str = "127.0.0.1", port: int = 8080, max_gaussians: int = 500_000):
    """Start serving ``run`` in the background; returns ``(server, handles)`` (``server.stop()`` ends it)."""
    import viser

    if max_gaussians < 1:
        raise InputError(None, "--max-gaussians", f"expected at least 1, got {max_gaussians}")
    if not 1 <= int(port) <= 65535:
        raise InputError(None, "--port", f"expected a port in 1-65535, got {port}")
    scene = load_run(run, max_gaussians)
    import socket

    try:  # viser binds in a thread and moves on to another port on failure: ask first
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
            probe.bind((host, int(port)))
    except OSError as e:
        raise InputError(None, "--port" if e.errno in (98, 48, 10048) else "--host", f"cannot listen on {host}:{port} ({e.strerror or e}); "
                         + ("choose another port" if e.errno in (98, 48, 10048) else "use an address of this machine, e.g. 127.0.0.1 or 0.0.0.0")) from None
    # browsers open and drop spare sockets (preconnects); websockets logs each as a failed handshake
    logging.getLogger("websockets.server").setLevel(logging.CRITICAL)
    with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner: serve() prints ours
        server = viser.ViserServer(host=host, port=port, label=f"mcgs-slam: {Path(run).resolve().name}", verbose=False)
    if server.get_port() != port:  # viser moves to the next free port; a user asked for this one
        stop(server)
        raise InputError(None, "--port", f"port {port} on {host} is in use; choose another port")
    return server, build_scene(server, scene)


def stop(server) -> None:
    """Stop a viewer started by :func:`start` (quietly)."""
    with contextlib.redirect_stdout(io.StringIO()):
        server.stop()


def serve(run, host: str = "127.0.0.1", port: int = 8080, max_gaussians: int = 500_000) -> None:
    """Serve ``run`` until interrupted."""
    server, handles = start(run, host, port, max_gaussians)
    url = f"http://{'localhost' if host in ('127.0.0.1', '0.0.0.0', '::') else host}:{port}"
    print(f"viewer of {run} at {url} ({len(handles['frusta'])} keyframe views); Ctrl-C stops it")
    if host in ("127.0.0.1", "localhost"):
        print(f"  from another machine: ssh -L {port}:localhost:{port} THIS_HOST, then open http://localhost:{port}")
    try:
        while True:
            time.sleep(1.0)
    finally:
        stop(server)
