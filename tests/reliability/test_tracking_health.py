"""Tracking health: a sequence whose frames jump (the rig teleports and turns between two
frames) is a tracking failure with one warning line naming the frame and a count in
metrics.json; the same sequence without the jump has none."""

import json

import numpy as np
import pytest

from mcgs_warp.data.synthetic import generate, rig_trajectory
from mcgs_warp.data.trajectory import Trajectory
from mcgs_warp.geometry import pose
from mcgs_warp.system.config import RunConfig
from mcgs_warp.system.run import run_sequence

JUMP_AT = 4


def config():
    cfg = RunConfig()
    cfg.tracking.mcba_iterations = 2
    cfg.mapping.iterations_per_keyframe = 2
    cfg.refinement.global_ba_iterations = 0
    cfg.refinement.iterations = 0
    cfg.output.renders = 0
    return cfg


def jumping_trajectory(n: int) -> Trajectory:
    """The built-in forward drive, teleported 4 m ahead and turned 50 degrees from frame JUMP_AT on."""
    traj = rig_trajectory(n)
    jump = pose(np.array([4.0, 0.6, 0.0]), np.array([0.0, 0.0, np.sin(np.radians(25)), np.cos(np.radians(25))]))
    poses = traj.poses.copy()
    poses[JUMP_AT:] = jump @ poses[JUMP_AT:]
    return Trajectory(traj.timestamps, poses)


@pytest.mark.parametrize("jump", [True, False], ids=["jump", "smooth"])
def test_a_jump_is_a_tracking_failure(tmp_path, capfd, jump):
    n = 7
    generate(tmp_path / "data", n_cameras=2, seed=3, progress=False, depth="exact", trajectory=jumping_trajectory(n) if jump else rig_trajectory(n))
    capfd.readouterr()
    metrics = run_sequence(tmp_path / "data", tmp_path / "run", config(), progress=False)
    err = capfd.readouterr().err
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    warnings = [line for line in err.splitlines() if "tracking failure" in line]
    if jump:
        assert saved["tracking_failures"] >= 1 and JUMP_AT in saved["tracking_failure_frames"], (saved, err)
        assert any(line.startswith(f"warning: frame {JUMP_AT} ") for line in warnings), err
        assert len(warnings) == saved["tracking_failures"]  # one line per failure
    else:
        assert saved["tracking_failures"] == 0 and not warnings, err
        assert metrics["ate_se3_rmse_m"] < 0.01
