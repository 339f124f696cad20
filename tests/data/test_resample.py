"""Processing resolution: resampled images keep the geometry (intrinsics scaled with the
OpenCV pixel-centre convention), depth takes the nearest sample."""

import numpy as np
import pytest

from mcgs_warp.data import FolderWriter, open_sequence
from mcgs_warp.data.resample import Resampled, at_processing_resolution, processing_scale
from mcgs_warp.rig import CameraSpec, Rig


def project(spec, X):
    fx, fy, cx, cy = spec.intrinsics
    return np.array([fx * X[0] / X[2] + cx, fy * X[1] / X[2] + cy])


def test_scaled_intrinsics_follow_the_image(tmp_path):
    spec = CameraSpec("c", "pinhole", 64, 40, (50.0, 52.0, 31.0, 18.5), distortion=(0.01, 0.0, 0.0, 0.0))
    # a bright pixel block at a known image point: its centroid moves as the intrinsics say
    X = np.array([0.21, -0.07, 1.0])
    u, v = project(spec, X)
    img = np.zeros((40, 64, 3), np.float32)
    r, c = int(round(v)), int(round(u))
    img[r - 1 : r + 3, c - 1 : c + 3] = 1.0  # 4x4 block, centre (c + 0.5, r + 0.5)
    rig = Rig([spec])
    w = FolderWriter(tmp_path / "seq", rig, depth_kind="exact")
    depth = np.full((40, 64), 2.0, np.float32)
    depth[:, 32:] = 5.0
    w.write_frame(0, [img], [depth])
    w.finish([0.0])
    seq = Resampled(open_sequence(tmp_path / "seq"), 0.5)
    small = seq.rig.cameras[0]
    assert (small.width, small.height) == (32, 20) and small.distortion == spec.distortion
    f = seq[0]
    g = f.images[0][..., 0]
    yy, xx = np.mgrid[: g.shape[0], : g.shape[1]]
    centroid = np.array([(g * xx).sum(), (g * yy).sum()]) / g.sum()
    np.testing.assert_allclose(centroid, [(c + 0.5 + 0.5) * 0.5 - 0.5, (r + 0.5 + 0.5) * 0.5 - 0.5], atol=1e-6)
    np.testing.assert_allclose(project(small, X), (np.array([u, v]) + 0.5) * 0.5 - 0.5, atol=1e-12)
    assert set(np.unique(f.depths[0])) == {2.0, 5.0}  # nearest: no invented depth between 2 and 5 m


def test_processing_scale_is_one_factor_for_the_rig():
    rig = Rig([CameraSpec("a", "pinhole", 1280, 720, (600.0, 600.0, 640.0, 360.0)), CameraSpec("b", "pinhole", 640, 480, (400.0, 400.0, 320.0, 240.0))])
    assert processing_scale(rig, 640) == pytest.approx(0.5)
    assert processing_scale(rig, 0) == 1.0 and processing_scale(rig, 2000) == 1.0
    seq = type("S", (), {"rig": rig})()
    assert at_processing_resolution(seq, 1280) is seq
