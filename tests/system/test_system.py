"""End to end: a short run on a tiny synthetic sequence produces every output, and the
exported USD / PLY / trajectories hold what the map and the estimate hold."""

import json
import subprocess
import sys

import numpy as np
import pytest

from mcgs_warp.data.synthetic import generate
from mcgs_warp.data.trajectory import Trajectory, read_tum, write_tum
from mcgs_warp.eval.trajectory import evaluate
from mcgs_warp.io.ply import SH_C0, read_ply
from mcgs_warp.io.usd import read_usd_map
from mcgs_warp.system.run import run_sequence
from run_configs import small_config

pytestmark = pytest.mark.slow  # runs the whole system: `pytest -m "not slow"` leaves it out


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("system")
    generate(root / "data", n_cameras=3, n_frames=6, seed=2, progress=False)
    metrics = run_sequence(root / "data", root / "run", small_config(renders=1), progress=False)
    return root, metrics


def cv2_read(path):
    import cv2

    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)


def test_run_writes_every_output(run_dir):
    root, metrics = run_dir
    run = root / "run"
    for name in ["trajectory.txt", "trajectory_odometry.txt", "trajectory_front.txt", "trajectory_left.txt", "trajectory_right.txt", "map.usdc", "map.ply", "metrics.json", "config.yaml", "rig.yaml", "keyframes.txt", "plots/trajectory.png", "plots/mapping.png"]:
        assert (run / name).is_file(), name
    assert list((run / "renders").glob("keyframe_*_front.png"))
    saved = json.loads((run / "metrics.json").read_text())
    for key in ["ate_rmse_m", "path_length_m", "psnr_db", "ssim", "depth_l1_m", "n_gaussians", "n_keyframes", "seconds_total"]:
        assert saved[key] is not None, key
    assert metrics["n_keyframes"] >= 3 and metrics["n_gaussians"] > 5000
    # What this run achieves (about 1.3 mm SE(3) on 0.8 m, scale 1.003, 30 dB), with a margin.
    assert metrics["ate_se3_rmse_m"] < 0.003 and abs(metrics["sim3_scale"] - 1) < 0.01, metrics
    # depth L1 here is against the exact depth the map was trained on (0.068 m): how well the
    # map renders its own target; depth it never saw is scored in tests/system/test_rgb_only.py
    assert metrics["psnr_db"] > 27 and metrics["depth_l1_m"] < 0.15 and metrics["depth_coverage"] > 0.95, metrics
    # the map covers every camera's view (a closed room: nothing is sky)
    cover = metrics["map_coverage_per_camera"]
    assert len(cover) == 3 and min(v["min"] for v in cover.values()) > 0.9, cover
    # exact depth measured every pixel: nothing the map renders was guessed (the confidence PNGs
    # say so); 5 % of the pixels mix surfaces at depth edges and carry 9x the error (0.56 vs 0.06 m)
    assert metrics["depth_l1_filled_m"] is None and metrics["depth_measured_fraction"] > 0.9 and min(metrics["measured_fraction_per_camera"].values()) > 0.9, metrics
    assert metrics["depth_l1_mixed_m"] > 4 * metrics["depth_l1_measured_m"], metrics
    # per camera against the exact depth: the median relative error the depth PNGs show (mm), on the pixels both have
    per_cam = metrics["depth_vs_exact_per_camera"]
    assert set(per_cam) == {"front", "left", "right"} and all(v["coverage"] > 0.95 and v["median_rel_measured"] <= v["median_rel"] + 0.002 for v in per_cam.values()), per_cam
    from mcgs_warp.data import open_sequence

    seq = open_sequence(root / "data")
    frame_of = {round(t, 6): i for i, t in enumerate(seq.timestamps)}
    rel = []
    for k, t in enumerate(read_tum(run / "keyframes.txt").timestamps):
        d = cv2_read(run / "depth" / f"keyframe_{k:03d}_front.png") / 1000.0
        true = seq.gt_depths(frame_of[round(t, 6)])[0]
        ok = (d > 0) & (true > 0)
        rel.append(np.abs(d[ok] - true[ok]) / true[ok])
    assert abs(np.median(np.concatenate(rel)) - per_cam["front"]["median_rel"]) < 0.002, (np.median(np.concatenate(rel)), per_cam)
    conf = sorted((run / "confidence").glob("keyframe_*.png"))
    assert len(conf) == 3 * metrics["n_keyframes"]
    import cv2

    c0 = cv2.imread(str(conf[0]), cv2.IMREAD_UNCHANGED)
    d0 = cv2.imread(str(run / "depth" / conf[0].name), cv2.IMREAD_UNCHANGED)
    assert c0.dtype == np.uint8 and c0.shape == d0.shape and set(np.unique(c0)) <= {0, 128, 255} and ((c0 > 0) == (d0 > 0)).all()
    assert metrics["loop_edges"] == 0  # six frames driving forward revisit nothing: an edge would be false
    assert metrics["tracking_failures"] == 0 and metrics["metric_scale"] is True
    traj = read_tum(run / "trajectory.txt")
    assert len(traj) == 6
    # frames the map was not fitted to: every non-keyframe view, rendered at its interpolated pose
    assert metrics["n_nonkeyframe_views"] == 3 * (6 - metrics["n_keyframes"]) > 0
    assert metrics["psnr_nonkeyframe_db"] > 26, metrics
    assert len(list((run / "renders").glob("frame_*_front.png"))) == 1
    # metrics.json holds what the written trajectory scores against the ground truth
    gt = read_tum(root / "data" / "groundtruth.txt")
    assert np.isclose(evaluate(traj, gt)[0].ate_rmse_m, saved["ate_rmse_m"], rtol=1e-6)
    se3 = evaluate(traj, gt, with_scale=False)[0]
    assert np.isclose(se3.ate_rmse_m, saved["ate_se3_rmse_m"], rtol=1e-6)
    # a metric run's RPE is unscaled (evo_rpe without --correct_scale), one frame apart
    assert saved["rpe_scale_corrected"] is False and saved["rpe_delta_frames"] == 1
    # (the file's 9 decimals bound a rotation to about 1e-7 degrees)
    assert np.isclose(saved["rpe_trans_m"], se3.rpe_trans_m, rtol=1e-6) and np.isclose(saved["rpe_rot_deg"], se3.rpe_rot_deg, rtol=1e-6, atol=1e-6)
    assert 0 < saved["rpe_trans_m"] < 0.01 and 0 < saved["rpe_rot_deg"] < 0.5, saved
    # keyframes only: the poses the run estimated (interpolated frames add their own error)
    kf = read_tum(run / "keyframes.txt")
    assert np.isclose(evaluate(kf, gt, with_scale=False)[0].ate_rmse_m, saved["ate_keyframes_se3_rmse_m"], rtol=1e-6)
    assert saved["ate_keyframes_se3_rmse_m"] < 0.002, saved
    # per-camera trajectories are the rig trajectory composed with the extrinsics
    from mcgs_warp.rig import load_rig

    rig = load_rig(run / "rig.yaml")
    cam = read_tum(run / "trajectory_left.txt")
    np.testing.assert_allclose(cam.poses, traj.poses @ rig.cameras[1].T_b_c, atol=1e-6)


def test_held_out_frames_are_evenly_spaced_non_keyframes():
    from mcgs_warp.system.outputs import held_out_frames

    assert held_out_frames(10, [0, 3, 9], max_frames=4) == [1, 4, 6, 8]
    assert held_out_frames(5, [0, 2, 4]) == [1, 3]
    assert held_out_frames(3, [0, 1, 2]) == []


def test_usd_map_agrees_with_the_ply(run_dir):
    run = run_dir[0] / "run"
    usd = read_usd_map(run / "map.usdc")
    ply = read_ply(run / "map.ply")
    np.testing.assert_allclose(usd["positions"], ply["means"], atol=1e-6)
    q = ply["quats"] / np.linalg.norm(ply["quats"], axis=1, keepdims=True)
    np.testing.assert_allclose(usd["orientations_wxyz"], np.concatenate([q[:, 3:], q[:, :3]], 1), atol=1e-6)
    np.testing.assert_allclose(usd["scales"], np.exp(ply["log_scales"]), rtol=1e-5)
    np.testing.assert_allclose(usd["opacities"], 1 / (1 + np.exp(-ply["opacity_logits"])), atol=1e-6)
    assert usd["opacities"].min() >= 0 and usd["opacities"].max() <= 1
    assert usd["sh_degree"] == 0
    np.testing.assert_allclose(usd["sh_coefficients"], (ply["colors"] - 0.5) / SH_C0, atol=1e-4)
    assert np.all(usd["extent"][0] <= ply["means"].min(0)) and np.all(usd["extent"][1] >= ply["means"].max(0))
    n_kf = json.loads((run / "metrics.json").read_text())["n_keyframes"]
    assert len(usd["cameras"]) == 3 * n_kf
    assert ply["measured"] is not None and ply["measured"].any()
    np.testing.assert_array_equal(usd["measured"], ply["measured"])


def test_export_command_round_trips(run_dir, tmp_path):
    run = run_dir[0] / "run"
    res = subprocess.run([sys.executable, "-m", "mcgs_warp", "export", "--run", str(run), "--usd", str(tmp_path / "m.usda"), "--ply", str(tmp_path / "m.ply")], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    a, b = read_ply(run / "map.ply"), read_ply(tmp_path / "m.ply")
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert len(read_usd_map(tmp_path / "m.usda")["positions"]) == len(a["means"])


def test_eval_matches_a_hand_computed_ate(tmp_path):
    """The estimate is a similarity transform of a circle; the ground truth is that
    circle plus alternating +-eps offsets along z, which are uncorrelated with the
    estimate, so the best alignment recovers the transform exactly and ATE = eps."""
    from mcgs_warp.geometry import pose, yaw_pitch_roll

    n, eps = 40, 0.03
    th = 2 * np.pi * np.arange(n) / n
    gt_p = np.stack([5 * np.cos(th), 5 * np.sin(th), np.zeros(n)], 1)
    q = np.tile([0, 0, 0, 1.0], (n, 1))
    noisy = gt_p + np.stack([np.zeros(n), np.zeros(n), eps * (-1.0) ** np.arange(n)], 1)
    gt = Trajectory(np.arange(n) * 0.1, pose(noisy, q))
    R, s, t = yaw_pitch_roll(0.7, 0.2, -0.1), 2.5, np.array([1.0, -2.0, 3.0])
    est = Trajectory(gt.timestamps + 0.001, pose((gt_p @ R.T) / s + t, q))
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", est)
    m, _, _ = evaluate(est, gt)
    assert abs(m.ate_rmse_m - eps) < 1e-7 and abs(m.scale - s) < 1e-6
    assert abs(m.path_length_m - np.linalg.norm(np.diff(noisy, axis=0), axis=1).sum()) < 1e-6
    res = subprocess.run([sys.executable, "-m", "mcgs_warp", "eval", "--est", str(tmp_path / "est.txt"), "--gt", str(tmp_path / "gt.txt"), "--json", str(tmp_path / "m.json"), "--plot", str(tmp_path / "p.png")], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert abs(json.loads((tmp_path / "m.json").read_text())["ate_rmse_m"] - eps) < 1e-6
    assert (tmp_path / "p.png").stat().st_size > 1000


def test_cli_errors_are_one_line_without_traceback(tmp_path):
    res = subprocess.run([sys.executable, "-m", "mcgs_warp", "eval", "--est", str(tmp_path / "none.txt"), "--gt", str(tmp_path / "none2.txt")], capture_output=True, text=True)
    assert res.returncode == 2 and "none.txt: trajectory file not found" in res.stderr and "Traceback" not in res.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracking:\n  window: [1\n")
    (tmp_path / "data").mkdir()
    res = subprocess.run([sys.executable, "-m", "mcgs_warp", "run", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "o"), "--config", str(bad)], capture_output=True, text=True)
    assert res.returncode == 2 and "bad.yaml: YAML syntax error" in res.stderr and "Traceback" not in res.stderr
    res = subprocess.run([sys.executable, "-m", "mcgs_warp", "run", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert res.returncode == 2 and "data folder is empty" in res.stderr and "Traceback" not in res.stderr


def test_examples_read_the_run(run_dir, tmp_path):
    """The USD-inspection and novel-view examples work on a run folder."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "examples"

    def load(name):
        spec = importlib.util.spec_from_file_location(name, root / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod

    run = run_dir[0] / "run"
    text = load("inspect_usd_map").describe(str(run / "map.usdc"))
    assert "ParticleField3DGaussianSplat" in text and "Gaussians" in text and "(Camera)" in text
    img = load("render_novel_view").render_novel(run, keyframe=1, shift=0.2, yaw_deg=5)
    assert img.shape[0] == 3 * 240 and img[..., :3].std() > 0.05
