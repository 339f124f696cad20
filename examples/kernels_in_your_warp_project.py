"""Use mcgs_warp.kernels from your own Warp project.

Renders a small cloud of Gaussians from a camera, then refines that camera's pose
from a perturbed start by gradient descent on the colour and depth error (RGB-D
tracking, as SplaTAM or the ODGS tracker do), using the
renderer's camera-pose gradient and the library's SE(3) ``wp.func`` helpers inside
a kernel of our own. Writes ``pose_from_gradients.png``: target | start | result.

    python examples/kernels_in_your_warp_project.py --out out/ [--device cuda:0]
"""

from __future__ import annotations

import argparse
import os
import zlib

import numpy as np
import warp as wp

from mcgs_warp.kernels import Gaussians, Views, make_camera, render, render_backward
from mcgs_warp.kernels.se3 import se3_exp, vec6


@wp.kernel
def retract_poses(T_w_c: wp.array(dtype=wp.transform), xi: wp.array(dtype=vec6)):
    """Right-multiplied update T_w_c <- T_w_c @ Exp(xi), xi = (rho, phi) in the camera frame."""
    c = wp.tid()
    T_w_c[c] = wp.transform_multiply(T_w_c[c], se3_exp(xi[c]))


def transform_to_matrix(t: np.ndarray) -> np.ndarray:
    x, y, z, w = t[3:]
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = t[:3]
    return T


def write_png(path: str, rgb: np.ndarray) -> None:
    """Minimal RGB8 PNG writer (keeps this example free of image libraries)."""
    img = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    raw = b"".join(b"\x00" + row.tobytes() for row in img)

    def chunk(tag, data):
        return len(data).to_bytes(4, "big") + tag + data + zlib.crc32(tag + data).to_bytes(4, "big")

    h, w = img.shape[:2]
    header = w.to_bytes(4, "big") + h.to_bytes(4, "big") + b"\x08\x02\x00\x00\x00"
    with open(path + ".tmp", "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))
    os.replace(path + ".tmp", path)


class Example:
    def __init__(self, device=None, n_gaussians=3000, seed=0, steps=150):
        rng = np.random.default_rng(seed)
        self.device = device
        self.camera = make_camera("pinhole", 160, 120, (140.0, 140.0, 79.5, 59.5), (-0.05, 0.01, 0.0, 0.0, 0.0))
        # A textured wall and a few blobs in front of it, 3-6 m ahead of the camera.
        n = n_gaussians
        means = np.stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(3, 6, n)], 1)
        colors = 0.5 + 0.5 * np.stack([np.sin(2 * means[:, 0]), np.cos(3 * means[:, 1]), np.sin(means[:, 2] * 4)], 1)
        self.gaussians = Gaussians.from_numpy(
            means, rng.normal(size=(n, 4)), np.log(rng.uniform(0.05, 0.2, (n, 3))), np.full(n, 1.0), colors, device
        )
        self.T_true = np.eye(4)
        target = render(self.gaussians, self._views(self.T_true))
        self.target, self.target_depth = target.color.numpy()[0], target.depth.numpy()[0]
        start = wp.transform(wp.vec3(0.08, -0.05, 0.1), wp.quat_rpy(0.02, -0.03, 0.02))
        self.pose = wp.array([start], dtype=wp.transform, device=device)
        self.start_image = self._render(self.matrix())
        self.loss = []
        self.adam_m = np.zeros(6)
        self.adam_v = np.zeros(6)
        self.steps = steps  # length of the learning-rate schedule

    def matrix(self) -> np.ndarray:
        return transform_to_matrix(self.pose.numpy()[0])

    def _views(self, T_w_c):
        return Views.create([self.camera], T_w_c[None], self.device)

    def _render(self, T_w_c) -> np.ndarray:
        """Colour image [H,W,3] seen from camera pose ``T_w_c``."""
        return render(self.gaussians, self._views(T_w_c)).color.numpy()[0]

    def step(self):
        views = self._views(self.matrix())
        out = render(self.gaussians, views)
        residual = out.color.numpy()[0] - self.target
        depth_residual = out.depth.numpy()[0] - self.target_depth
        depth_weight = 0.1  # per m^2, relative to colour
        self.loss.append(float(np.mean(residual**2) + depth_weight * np.mean(depth_residual**2)))
        grads = render_backward(
            self.gaussians,
            views,
            out,
            grad_color=(2.0 / residual.size) * residual[None],
            grad_depth=(2.0 * depth_weight / depth_residual.size) * depth_residual[None],
        )
        # Adam on the tangent-space gradient, then retract on the manifold.
        g = grads.pose.numpy()[0].astype(np.float64)
        k = len(self.loss)
        self.adam_m = 0.9 * self.adam_m + 0.1 * g
        self.adam_v = 0.999 * self.adam_v + 0.001 * g * g
        lr = 1e-4 + 0.5 * (4e-3 - 1e-4) * (1 + np.cos(np.pi * min(k / self.steps, 1.0)))  # cosine decay
        step = -lr * (self.adam_m / (1 - 0.9**k)) / (np.sqrt(self.adam_v / (1 - 0.999**k)) + 1e-12)
        xi = wp.array(step[None].astype(np.float32), dtype=vec6, device=self.device)
        wp.launch(retract_poses, dim=1, inputs=[self.pose, xi], device=self.device)

    def render(self, path: str):
        write_png(path, np.concatenate([self.target, self.start_image, self._render(self.matrix())], axis=1))

    def pose_error(self):
        d = np.linalg.inv(self.T_true) @ self.matrix()
        angle = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
        return float(np.linalg.norm(d[:3, 3])), float(angle)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: Warp's default)")
    parser.add_argument("--out", default="out", help="output folder")
    parser.add_argument("--steps", type=int, default=150)
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    example = Example(args.device, steps=args.steps)
    t0, r0 = example.pose_error()
    print(f"start:  pose error {t0 * 100:.1f} cm, {r0:.2f} deg")
    for k in range(args.steps):
        example.step()
        if k % 25 == 0:
            print(f"step {k:4d}  loss {example.loss[-1]:.6f}")
    t1, r1 = example.pose_error()
    print(f"result: pose error {t1 * 100:.1f} cm, {r1:.2f} deg")
    path = os.path.join(args.out, "pose_from_gradients.png")
    example.render(path)
    print(f"wrote {path}")
