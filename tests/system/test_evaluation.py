"""Trajectory metrics against closed-form answers: evo-style relative pose error."""

import numpy as np
import pytest

from mcgs_warp.data.trajectory import Trajectory
from mcgs_warp.eval.trajectory import evaluate, relative_pose_error, rotation_angle
from mcgs_warp.geometry import pose, se3_exp, yaw_pitch_roll


def random_walk(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = [np.eye(4)]
    for _ in range(n - 1):
        T.append(T[-1] @ se3_exp(np.concatenate([rng.normal(0, 0.3, 3), rng.normal(0, 0.1, 3)])))
    return np.array(T)


def test_rotation_angle_is_accurate_from_zero_to_pi():
    for angle in (1e-9, 1e-4, 0.3, 2.0, np.pi - 1e-6):
        R = se3_exp(np.array([0, 0, 0, 0.6, -0.8, 0.0]) * angle)[:3, :3]
        assert rotation_angle(R) == pytest.approx(angle, rel=1e-6)


def test_rpe_recovers_a_known_per_step_error_and_ignores_the_alignment():
    """Each estimated step is the true step times a fixed error D: every relative pose
    error of delta 1 is D, so RPE = (|t_D|, angle(R_D)) exactly, whatever rigid or similarity
    transform the whole estimate is in (and the scale, with with_scale)."""
    n = 30
    Q = random_walk(n, 0)
    D = se3_exp(np.array([0.02, -0.01, 0.005, 0.0, 0.01, 0.004]))
    P = [Q[0]]
    for i in range(n - 1):
        P.append(P[-1] @ np.linalg.inv(Q[i]) @ Q[i + 1] @ D)
    P = np.array(P)
    t_true, r_true = np.linalg.norm(D[:3, 3]), np.degrees(rotation_angle(D[:3, :3]))
    assert relative_pose_error(P, Q) == pytest.approx((t_true, r_true), rel=1e-9)
    # the same estimate in another world frame and at 1/3 the scale
    G = np.eye(4)
    G[:3, :3], G[:3, 3] = yaw_pitch_roll(0.7, -0.2, 0.4), [3.0, -1.0, 2.0]
    s = 1 / 3
    moved = G @ P
    moved[:, :3, 3] *= s
    stamps = np.arange(n) * 0.1
    assert relative_pose_error(moved, Q, scale=1 / s) == pytest.approx((t_true, r_true), rel=1e-9)
    # evaluate() corrects by its Sim(3) scale (near 1/s: the drift moves it a little)
    m, _, _ = evaluate(Trajectory(stamps, moved), Trajectory(stamps, Q))
    assert m.scale == pytest.approx(1 / s, rel=0.05) and m.rpe_delta == 1
    assert (m.rpe_trans_m, m.rpe_rot_deg) == pytest.approx(relative_pose_error(moved, Q, scale=m.scale), rel=1e-12)
    assert m.rpe_rot_deg == pytest.approx(r_true, rel=1e-9)
    # SE(3): the scale is not corrected, so the translation error is what a user measures
    se3, _, _ = evaluate(Trajectory(stamps, moved), Trajectory(stamps, Q), with_scale=False)
    assert se3.rpe_rot_deg == pytest.approx(r_true, rel=1e-9) and se3.rpe_trans_m > 5 * t_true


def test_rpe_delta_compares_poses_delta_apart():
    """A single corrupted pose k: with delta d, the pairs (k-d, k) and (k, k+d) see its error,
    every other pair none; a drift-free translation offset e at pose k gives RMSE
    sqrt(2 e^2 / (n - d)) for any d."""
    n, e = 20, 0.05
    Q = random_walk(n, 1)
    P = Q.copy()
    P[7] = P[7] @ pose(np.array([e, 0, 0]), np.array([0, 0, 0, 1.0]))
    for d in (1, 3):
        t, r = relative_pose_error(P, Q, delta=d)
        assert t == pytest.approx(np.sqrt(2 * e**2 / (n - d)), rel=1e-9) and r == pytest.approx(0, abs=1e-6)
    assert np.isnan(relative_pose_error(P[:3], Q[:3], delta=3)[0])
    with pytest.raises(ValueError):
        relative_pose_error(P, Q, delta=0)


def test_a_metric_run_far_from_scale_one_is_told_to_check_its_depth_unit():
    from mcgs_warp.system.outputs import scale_warning

    assert scale_warning(True, 1.05) is None and scale_warning(False, 0.2) is None
    why = scale_warning(True, 0.2)  # TUM depth (5000 per metre) read as millimetres: 5x too far
    assert "0.200" in why and "millimetres" in why and "1/5000" in why


def test_a_run_with_too_few_ground_truth_poses_still_writes_its_metrics(tmp_path, capfd):
    """Ground truth that matches only 2 of the run's poses (a 2-keyframe nuScenes scene): one
    warning, metrics.json with everything but the trajectory figures, and the command exits 0."""
    import json
    import subprocess
    import sys

    from mcgs_warp.data.synthetic import generate

    generate(tmp_path / "data", n_cameras=1, n_frames=3, seed=2, progress=False, depth="exact")
    gt = (tmp_path / "data" / "groundtruth.txt").read_text().splitlines()
    rows = [line for line in gt if line.strip() and not line.startswith("#")]
    (tmp_path / "data" / "groundtruth.txt").write_text("\n".join(rows[:2]) + "\n")
    (tmp_path / "fast.yaml").write_text("tracking:\n  mcba_iterations: 1\nmapping:\n  iterations_per_keyframe: 1\nrefinement:\n  iterations: 0\n  global_ba_iterations: 0\noutput:\n  renders: 0\n")
    res = subprocess.run([sys.executable, "-m", "mcgs_warp", "run", "--data", tmp_path / "data", "--out", tmp_path / "run", "--config", tmp_path / "fast.yaml"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stderr.count("trajectory not evaluated: only 2 estimated poses match") == 1, res.stderr
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["ate_rmse_m"] is None and "ate_se3_rmse_m" not in m and m["psnr_db"] > 10 and m["n_frames"] == 3


def test_relative_errors_median_is_the_pixels_median_within_a_bin():
    """The per-camera depth metric's histogram gives the median of the pixels it was fed
    (in parts, as keyframe views add them) within its 0.05 % bins; beyond 200 % it says 2.0 (no
    infinity: metrics.json stays standard JSON)."""
    from mcgs_warp.system.outputs import RelativeErrors

    rng = np.random.default_rng(0)
    parts = [rng.lognormal(-3, 1, n) for n in (1000, 5, 20000)]
    h = RelativeErrors()
    assert h.median() is None
    for p in parts:
        h.add(p)
    assert abs(h.median() - np.median(np.concatenate(parts))) <= RelativeErrors.BIN
    far = RelativeErrors()
    far.add(np.array([0.1, 3.0, 5.0]))
    assert far.median() == 2.0
