"""The kernels example runs headless and its pose gradient descent makes progress."""

import importlib.util
from pathlib import Path

import numpy as np

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "kernels_in_your_warp_project.py"


def test_example_recovers_pose_and_writes_png(tmp_path):
    spec = importlib.util.spec_from_file_location("kernels_example", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    example = module.Example(device="cpu", n_gaussians=1500, steps=60)
    t0, r0 = example.pose_error()
    for _ in range(60):
        example.step()
    t1, r1 = example.pose_error()
    assert example.loss[-1] < 0.1 * example.loss[0]
    assert t1 < 0.6 * t0 and r1 < 0.6 * r0, (t0, r0, t1, r1)
    path = tmp_path / "pose.png"
    example.render(str(path))
    data = path.read_bytes()
    assert data.startswith(b"\x89PNG") and len(data) > 1000
    assert np.isfinite(example.matrix()).all()
