"""The built-in synthetic sequence written as EuRoC MAV, KITTI odometry and TUM RGB-D
(tests/system/formats.py), read back by our readers and run end to end: each reader gives
the source's rig, frames and ground truth, and each run tracks the sequence at metric scale."""

import numpy as np
import pytest

from mcgs_warp.data import open_sequence
from mcgs_warp.data.euroc import EurocSequence
from mcgs_warp.data.kitti import KittiSequence
from mcgs_warp.data.synthetic import generate
from mcgs_warp.data.tum import TumSequence
from mcgs_warp.system.run import run_sequence
from run_configs import small_config
from formats import stereo_rig, write_euroc, write_kitti, write_tum

pytestmark = pytest.mark.slow  # runs the whole system: `pytest -m "not slow"` leaves it out

N_FRAMES = 8


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    root = tmp_path_factory.mktemp("formats")
    return root, generate(root / "ours", n_frames=N_FRAMES, seed=3, progress=False, rig=stereo_rig())


def grey(img):
    import cv2

    return cv2.cvtColor((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2GRAY) / 255.0


def relative(T):
    return np.linalg.inv(T[0]) @ T


@pytest.mark.parametrize("layout", ["euroc", "kitti", "tum"])
def test_dataset_layouts_read_back_and_run(source, layout):
    root, seq = source
    write = {"euroc": write_euroc, "kitti": write_kitti, "tum": write_tum}[layout]
    data = write(seq, root / layout)
    got = open_sequence(data)
    assert isinstance(got, {"euroc": EurocSequence, "kitti": KittiSequence, "tum": TumSequence}[layout])
    assert len(got) == N_FRAMES
    np.testing.assert_allclose(got.timestamps - got.timestamps[0], seq.timestamps - seq.timestamps[0], atol=1e-6)
    cams = [0] if layout == "tum" else [0, 1]
    body = seq.rig.cameras[0].T_b_c if layout in ("kitti", "tum") else np.eye(4)  # KITTI's body is camera 0, TUM's the camera
    for c in cams:
        a, b = got.rig.cameras[c], seq.rig.cameras[c]
        assert a.intrinsics == pytest.approx(b.intrinsics) and (a.width, a.height) == (b.width, b.height)
        np.testing.assert_allclose(a.T_b_c, np.linalg.inv(body) @ b.T_b_c, atol=1e-9)
    # ground truth: the same motion of the reader's body
    np.testing.assert_allclose(relative(got.groundtruth.poses), relative(seq.groundtruth.poses @ body), atol=1e-6)
    f, g = got[N_FRAMES // 2], seq[N_FRAMES // 2]
    for c in cams:
        if layout == "tum":
            np.testing.assert_allclose(f.images[c], g.images[c], atol=0.6 / 255)
            exact = seq.gt_depths(N_FRAMES // 2)[c]
            near = exact < 65535 / 5000  # what 16 bits at 5000 per metre hold
            np.testing.assert_allclose(f.depths[c][near], exact[near], atol=0.2e-3 + 1e-6)  # 1/5000 m steps
            assert near.mean() > 0.5 and not f.depths[c][~near].any()
        else:
            np.testing.assert_allclose(f.images[c][..., 1], grey(g.images[c]), atol=0.6 / 255)
            assert f.depths[c] is None
    m = run_sequence(data, root / f"run_{layout}", small_config(mcba_iterations=3, global_ba_iterations=2), progress=False)
    assert m["depth_source"] == ("sensor" if layout == "tum" else "stereo") and m["metric_scale"] is True
    assert m["n_keyframes"] >= 3 and m["tracking_failures"] == 0, m
    # measured: SE(3) ATE 0.15 % (EuRoC), 0.16 % (KITTI), 0.21 % (TUM) of the path, scale within 0.3 %
    limit = 0.0045 if layout == "tum" else 0.003
    assert m["ate_se3_rmse_m"] < limit * m["path_length_m"] and abs(m["sim3_scale"] - 1) < 0.005, m


def test_bag_of_the_sequence_runs_end_to_end(source):
    """The sequence written as a ROS 1 bag (mcgs-slam bag) and run with its rig tracks at
    metric scale from the rig stereo, as the folder does (the bag gives the folder's frames
    bit for bit: tests/data/test_rosbag.py)."""
    from mcgs_warp.data import read_tum
    from mcgs_warp.data.rosbag import write_bag
    from mcgs_warp.eval.trajectory import evaluate

    root, seq = source
    bag, rig = write_bag(seq, root / "recording.bag")
    m = run_sequence(bag, root / "run_bag", small_config(mcba_iterations=3, global_ba_iterations=2), rig=rig, progress=False)
    assert m["depth_source"] == "stereo" and m["metric_scale"] is True and m["n_keyframes"] >= 3 and m["tracking_failures"] == 0, m
    # the bag carries no ground truth: the folder's, against the bag run's trajectory
    se3 = evaluate(read_tum(root / "run_bag" / "trajectory.txt"), seq.groundtruth, with_scale=False)[0]
    assert se3.ate_rmse_m < 0.003 * m["path_length_m"], (se3.ate_rmse_m, m["path_length_m"])
