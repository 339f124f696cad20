"""Every benchmark script starts as its docstring says (``python benchmarks/<name>.py``): it
imports (no file in benchmarks/ shadows a module of the standard library or a dependency, as
a ``profile.py`` there once shadowed the one cProfile imports) and parses its arguments."""

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = sorted((Path(__file__).resolve().parents[2] / "benchmarks").glob("*.py"))


def test_no_benchmark_shadows_a_module_it_imports():
    import importlib.util

    shadowing = [p.name for p in BENCHMARKS if p.stem in sys.stdlib_module_names or importlib.util.find_spec(p.stem) is not None]  # (run from the repository root: benchmarks/ is not on the path)
    assert not shadowing, shadowing


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.stem)
def test_benchmark_prints_its_usage(script):
    res = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and "usage" in res.stdout, res.stderr[-2000:]


def test_real_benchmark_scores_a_scale_bias_in_every_segment():
    """benchmarks/real.py's scoring: an estimate 1 % long (a stereo scale bias) shows as path ratio
    1.01 in every 10-frame segment and Sim(3) scale 1/1.01, with zero Sim(3) ATE; its table
    prints a skipped row with the reason."""
    import importlib.util

    import numpy as np

    from mcgs_warp.data.trajectory import Trajectory
    from mcgs_warp.geometry import se3_exp

    spec = importlib.util.spec_from_file_location("real_benchmark", Path(__file__).resolve().parents[2] / "benchmarks" / "real.py")
    real = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(real)
    rng = np.random.default_rng(0)
    T = [np.eye(4)]
    for _ in range(34):
        T.append(T[-1] @ se3_exp(np.r_[0.0, 0.0, 1.2, rng.normal(0, 0.02, 3)]))
    gt = Trajectory(np.arange(35) * 0.1, np.stack(T))
    est = Trajectory(gt.timestamps, gt.poses.copy())
    est.poses[:, :3, 3] *= 1.01
    f = real.figures(est, gt)
    assert abs(f["path_ratio"] - 1.01) < 1e-9 and len(f["segments"]) == 4 and np.allclose(f["segments"], 1.01, atol=1e-4)
    assert abs(f["scale"] - 1 / 1.01) < 1e-9 and f["sim3_m"] < 1e-9 and f["se3_m"] > 0.05
    text = real.table([{"sequence": "s", "every": 3, "frames": 1, "method": "ours", "skipped": "every 3 keeps 1 of its 3 frames"}, {"sequence": "s", "every": 1, "method": "odometry", **f}])
    assert "every 3 keeps 1" in text and "1.0100-1.0100" in text


def test_ab_runs_both_revisions_alternately_in_their_own_trees(tmp_path):
    """benchmarks/ab.py: each revision's command runs in its own worktree (its own code imports),
    alternating old, new, old, new, with {out} a fresh folder per run whose metrics it prints; the
    summary is the ratio of median times."""
    repo = Path(__file__).resolve().parents[2]
    if subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True).returncode != 0:
        pytest.skip("not a git checkout")
    def trees():
        return subprocess.run(["git", "-C", str(repo), "worktree", "list"], capture_output=True, text=True).stdout

    before = trees()
    log = tmp_path / "order.txt"
    code = ("import json, os, pathlib, sys, mcgs_warp, mcgs_warp.kernels; out = pathlib.Path(sys.argv[1]); out.mkdir(parents=True); "
            "(out / 'metrics.json').write_text(json.dumps({'ate_se3_rmse_m': 0.1234, 'psnr_db': 22.5, 'psnr_nonkeyframe_db': None})); "
            f"open({str(log)!r}, 'a').write(str(pathlib.Path(mcgs_warp.__file__).parents[1] != pathlib.Path({str(repo)!r})) + ' ' + out.name + chr(10))")
    res = subprocess.run([sys.executable, str(repo / "benchmarks" / "ab.py"), "HEAD", "HEAD", "--out", str(tmp_path / "ab"), "--", "python", "-c", code, "{out}"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert log.read_text().split() == ["True", "old_0", "True", "new_0", "True", "old_1", "True", "new_1"]  # each run imported its worktree's package, not this checkout's
    assert res.stdout.count("SE(3) 0.1234 m, PSNR 22.50 / – dB") == 4 and "new/old = " in res.stdout, res.stdout
    assert trees() == before  # its worktrees are gone


def test_stage_profile_charges_opencv_time_to_the_running_stage():
    """benchmarks/stage_profile.py: an OpenCV function and a method of an object an OpenCV factory
    made (SIFT, DIS flow) charge their wall time to the stage running, once when nested, and
    not when another thread calls them; Python around them is not charged."""
    import importlib.util
    import threading
    import time
    import types

    spec = importlib.util.spec_from_file_location("stage_profile", Path(__file__).resolve().parents[2] / "benchmarks" / "stage_profile.py")
    sp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sp)

    class Flow:
        def calc(self, s):
            time.sleep(s)

    cv = types.SimpleNamespace(sleep=time.sleep, Flow_create=Flow)
    clock = sp.StageClock()
    clock.opencv(cv)
    flow = cv.Flow_create()
    nested = clock.native_time(lambda: cv.sleep(0.05), clock.kernel)  # OpenCV inside a timed kernel launch: the launch's, once
    step = clock.stage("keyframe step", lambda: (cv.sleep(0.05), flow.calc(0.05), nested(), time.sleep(0.2)))
    step()
    t = threading.Thread(target=cv.sleep, args=(0.05,))
    t.start()
    t.join()
    assert 0.1 <= clock.cv["keyframe step"] < 0.145 and set(clock.cv) == {"keyframe step"}, clock.cv
    assert 0.05 <= clock.kernel["keyframe step"] < 0.095, clock.kernel
    assert clock.seconds["keyframe step"] >= 0.35
