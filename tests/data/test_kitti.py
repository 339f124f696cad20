"""KITTI odometry reader on fixture folders (both layouts), and on the real excerpt in
../shared/data when it is there."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from mcgs_warp.data import open_sequence
from mcgs_warp.data.kitti import KittiSequence
from mcgs_warp.errors import InputError

# KITTI odometry sequences 00-02: P0..P3 (rectified; P2/P3 are the colour cameras, offset from camera 0)
CALIB = """P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P1: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.861448000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P2: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 4.538225000000e+01 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 -1.130887000000e-01 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 3.779761000000e-03
P3: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.372877000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 2.369057000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 4.915215000000e-03
Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 -7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01
"""

EXCERPT = Path(__file__).resolve().parents[3] / "shared" / "data" / "kitti_stereo_excerpt"


def make_kitti(seq_dir: Path, n=3, w=62, h=19, colour=True, poses_inside=True):
    rng = np.random.default_rng(0)
    for i in (0, 1, 2, 3) if colour else (0, 1):
        (seq_dir / f"image_{i}").mkdir(parents=True)
        for k in range(n):
            shape = (h, w, 3) if i >= 2 else (h, w)
            cv2.imwrite(str(seq_dir / f"image_{i}" / f"{k:06d}.png"), rng.integers(0, 255, shape, dtype=np.uint8))
    (seq_dir / "calib.txt").write_text(CALIB)
    (seq_dir / "times.txt").write_text("".join(f"{0.1036 * k:.6e}\n" for k in range(n)))
    poses = [np.hstack([np.eye(3), [[0.01 * k], [-0.002 * k], [1.1 * k]]]) for k in range(n)]
    text = "".join(" ".join(f"{v:.6e}" for v in P.ravel()) + "\n" for P in poses)
    if poses_inside:
        (seq_dir / "poses.txt").write_text(text)
    else:
        (seq_dir.parent.parent / "poses").mkdir(parents=True, exist_ok=True)
        (seq_dir.parent.parent / "poses" / f"{seq_dir.name}.txt").write_text(text)
    return seq_dir


def test_grey_pair_rig_and_ground_truth(tmp_path):
    root = make_kitti(tmp_path / "excerpt")
    seq = open_sequence(root)
    assert isinstance(seq, KittiSequence) and len(seq) == 3 and len(seq.rig) == 2
    left, right = seq.rig.cameras
    assert left.intrinsics == (718.856, 718.856, 607.1928, 185.2157) and (left.width, left.height) == (62, 19)
    np.testing.assert_allclose(left.T_b_c, np.eye(4), atol=1e-12)
    # the right camera sits 386.1448 / 718.856 = 0.5372 m to the right of camera 0 (the body)
    np.testing.assert_allclose(right.T_b_c[:3, 3], [386.1448 / 718.856, 0, 0], atol=1e-12)
    f = seq[2]
    assert f.images[0].shape == (19, 62, 3) and np.allclose(f.images[0][..., 0], f.images[0][..., 2])
    assert f.depths == [None, None]
    np.testing.assert_allclose(seq.timestamps, [0, 0.1036, 0.2072])
    np.testing.assert_allclose(seq.groundtruth.positions[2], [0.02, -0.004, 2.2])
    # a point seen by camera 0 projects where P1 puts it in camera 1
    X = np.array([1.5, -0.4, 12.0, 1.0])
    P1 = np.array(CALIB.splitlines()[1].split()[1:], float).reshape(3, 4)
    u = P1 @ X
    x_c1 = np.linalg.inv(right.T_b_c) @ X
    fx, fy, cx, cy = right.intrinsics
    np.testing.assert_allclose([fx * x_c1[0] / x_c1[2] + cx, fy * x_c1[1] / x_c1[2] + cy], u[:2] / u[2], atol=1e-9)


def test_colour_pair_and_full_kitti_layout(tmp_path):
    root = make_kitti(tmp_path / "dataset" / "sequences" / "00", poses_inside=False)
    seq = open_sequence(root, kitti_cameras="colour")
    assert [c.name for c in seq.rig.cameras] == ["image_2", "image_3"]
    f = seq[0]
    raw = cv2.imread(str(root / "image_2" / "000000.png"))[..., ::-1] / 255.0
    np.testing.assert_allclose(f.images[0], raw, atol=1e-6)  # colour, RGB order
    # P2 = K [I | t]: its centre is -t, with t = K^-1 P2[:, 3]
    P2 = np.array(CALIB.splitlines()[2].split()[1:], float).reshape(3, 4)
    np.testing.assert_allclose(seq.rig.cameras[0].T_b_c[:3, 3], -np.linalg.solve(P2[:, :3], P2[:, 3]), atol=1e-12)
    assert seq.groundtruth is not None and len(seq.groundtruth) == 3  # from ../../poses/00.txt


def test_all_four_cameras_as_one_rig(tmp_path):
    """``--kitti-cameras all``: image_0 to image_3 as one 4-camera rig, each camera where its
    projection puts it (grey pair, then colour pair), grey images as RGB and colour ones in RGB
    order; without the colour folders it says which it needs."""
    root = make_kitti(tmp_path / "s")
    seq = open_sequence(root, kitti_cameras="all")
    assert [c.name for c in seq.rig.cameras] == ["image_0", "image_1", "image_2", "image_3"]
    lines = CALIB.splitlines()
    for c, spec in enumerate(seq.rig.cameras):
        P = np.array(lines[c].split()[1:], float).reshape(3, 4)
        np.testing.assert_allclose(spec.T_b_c[:3, 3], -np.linalg.solve(P[:, :3], P[:, 3]), atol=1e-12)
        np.testing.assert_allclose(spec.T_b_c[:3, :3], np.eye(3), atol=1e-12)
    f = seq[1]
    assert len(f.images) == 4 and f.depths == [None] * 4
    np.testing.assert_allclose(f.images[0][..., 0], cv2.imread(str(root / "image_0" / "000001.png"), cv2.IMREAD_GRAYSCALE) / 255.0, atol=1e-6)
    np.testing.assert_allclose(f.images[3], cv2.imread(str(root / "image_3" / "000001.png"))[..., ::-1] / 255.0, atol=1e-6)
    grey_only = make_kitti(tmp_path / "g", colour=False)
    with pytest.raises(InputError, match=r"image_2: missing image folder \(all four cameras need image_0 to image_3\)"):
        open_sequence(grey_only, kitti_cameras="all")


def test_bad_kitti_folders(tmp_path):
    root = make_kitti(tmp_path / "s", colour=False)
    with pytest.raises(InputError, match=r"image_2: missing image folder \(the colour pair needs image_2 and image_3\)"):
        open_sequence(root, kitti_cameras="colour")
    (root / "calib.txt").write_text(CALIB.replace("P1: 7.188560000000e+02 ", "P1: "))
    with pytest.raises(InputError, match=r"calib.txt: P1: expected 12 finite numbers"):
        open_sequence(root)
    (root / "calib.txt").write_text(CALIB)
    (root / "poses.txt").write_text((root / "poses.txt").read_text().splitlines()[0] + "\n")
    with pytest.raises(InputError, match=r"poses.txt: lists 1 poses but times.txt lists 3 frames"):
        open_sequence(root)
    (root / "poses.txt").unlink()
    (root / "image_1" / "000002.png").unlink()
    with pytest.raises(InputError, match=r"image_1: holds 2 images but times.txt lists 3 frames"):
        open_sequence(root)


@pytest.mark.skipif(not EXCERPT.is_dir(), reason="the KITTI excerpt lives in ../shared/data (KITTI's licence keeps it out of the repo)")
def test_real_kitti_excerpt():
    seq = open_sequence(EXCERPT)
    assert len(seq) == 51 and [(c.width, c.height) for c in seq.rig.cameras] == [(1241, 376)] * 2
    assert np.linalg.norm(seq.rig.cameras[1].T_b_c[:3, 3]) == pytest.approx(0.537, abs=1e-3)
    steps = np.linalg.norm(np.diff(seq.groundtruth.positions, axis=0), axis=1)
    assert 0.9 < steps.min() and steps.max() < 1.3  # the README's 0.95-1.27 m per frame
