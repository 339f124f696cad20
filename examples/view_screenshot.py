"""Screenshot of a run's map in the web viewer, taken by headless Chromium.

    mcgs-slam demo --out demo
    python examples/view_screenshot.py demo/run --out docs/viewer.png

Starts ``mcgs-slam view``'s server on a free local port, opens it in headless Chromium
(WebGL through SwiftShader: no GPU or display needed), waits for the browser to connect,
puts its camera behind and above the first keyframe looking down the trajectory, and saves
what the browser drew. Chromium is looked for as ``$CHROMIUM``, ``chromium``,
``chromium-browser``, ``google-chrome``; where none is found the script says so and exits
with code 2 (on Debian: ``apt-get install chromium``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium() -> str | None:
    env = os.environ.get("CHROMIUM")
    if env:
        return env if Path(env).is_file() or shutil.which(env) else None
    return next((shutil.which(c) for c in CANDIDATES if shutil.which(c)), None)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def overview_pose(scene):
    """A camera behind and above the first keyframe, looking at the trajectory's middle."""
    up = scene.up
    traj = scene.trajectory if scene.trajectory is not None and len(scene.trajectory) > 1 else scene.centers
    start, middle = traj[0], traj[len(traj) // 2]
    span = max(float(np.linalg.norm(traj[-1] - traj[0])), 1.0)
    forward = middle - start
    forward = forward - up * (forward @ up)
    forward = forward / max(np.linalg.norm(forward), 1e-9) if np.linalg.norm(forward) > 1e-9 else np.cross(up, [1.0, 0, 0])
    eye = start - 0.6 * span * forward + 0.5 * span * up
    return eye, middle


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="run folder (e.g. demo/run)")
    parser.add_argument("--out", default="viewer.png", help="PNG to write (default viewer.png)")
    parser.add_argument("--size", default="1280x800", help="browser window, WIDTHxHEIGHT (default 1280x800)")
    parser.add_argument("--keyframe", default=None, help="look through this keyframe view instead, e.g. 'keyframe 3 / front'")
    parser.add_argument("--timeout", type=float, default=90.0, help="seconds to wait for the browser (default 90)")
    args = parser.parse_args(argv)

    chromium = find_chromium()
    if chromium is None:
        print("view_screenshot: Chromium not found (looked for $CHROMIUM, " + ", ".join(CANDIDATES) + "); "
              "install it (Debian/Ubuntu: apt-get install chromium) or set CHROMIUM=/path/to/chrome", file=sys.stderr)
        return 2
    from mcgs_warp.io import write_image
    from mcgs_warp.viewer import load_run, start, stop

    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
        assert width > 0 and height > 0
    except (ValueError, AssertionError):
        parser.error(f"--size: expected WIDTHxHEIGHT like 1280x800, got {args.size!r}")
    scene = load_run(args.run, max_gaussians=1)  # errors name the file before anything starts
    if args.keyframe and args.keyframe not in [label for label, *_ in scene.cameras]:
        labels = [label for label, *_ in scene.cameras]
        parser.error(f"--keyframe: expected a view like {labels[0]!r}, got {args.keyframe!r}" if labels else "--keyframe: the run has no keyframe cameras")
    port = free_port()
    server, handles = start(args.run, port=port)
    profile = tempfile.mkdtemp(prefix="mcgs-chromium-")
    flags = ["--headless=new", "--no-sandbox", "--no-first-run", "--disable-background-networking", "--disable-component-update",
             "--disable-sync", "--disable-quic", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
             f"--window-size={width},{height}", f"--user-data-dir={profile}", f"http://127.0.0.1:{port}/"]
    browser = None
    try:
        browser = subprocess.Popen([chromium, *flags], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        end = time.time() + args.timeout
        while not server.get_clients() and time.time() < end:
            if browser.poll() is not None:
                print(f"view_screenshot: {chromium} exited with code {browser.returncode} before connecting", file=sys.stderr)
                return 1
            time.sleep(0.2)
        clients = list(server.get_clients().values())
        if not clients:
            print(f"view_screenshot: the browser did not connect within {args.timeout:g} s", file=sys.stderr)
            return 1
        client = clients[0]
        time.sleep(3.0)  # the scene's messages arrive and the splats sort once
        if args.keyframe:
            handles["look_through"](args.keyframe, [client])
        else:
            eye, target = overview_pose(scene)
            client.camera.up_direction = tuple(scene.up)
            client.camera.position = eye
            client.camera.look_at = target
        time.sleep(3.0)
        image = client.camera.get_render(height=height, width=width, transport_format="png")
        write_image(args.out, image[..., :3].astype(np.float32) / 255.0)
        print(f"wrote {args.out} ({width}x{height}) from {chromium}")
        return 0
    finally:
        if browser is not None:
            browser.terminate()
            try:
                browser.wait(10)
            except subprocess.TimeoutExpired:
                browser.kill()
        stop(server)
        shutil.rmtree(profile, ignore_errors=True)


if __name__ == "__main__":
    from mcgs_warp.errors import InputError

    try:
        sys.exit(main())
    except InputError as e:  # a missing or broken run folder: one line, as the command line says it
        print(f"view_screenshot: error: {e}", file=sys.stderr)
        sys.exit(2)
