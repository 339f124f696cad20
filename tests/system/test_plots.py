"""The plots are real PNGs of the stated size, with a legend and an error colorbar, written
atomically; `eval --plot` draws the run's trajectory figure; pyplot is never imported."""

import subprocess
import sys

import numpy as np
import pytest

from mcgs_warp.cli import main
from mcgs_warp.data.trajectory import Trajectory, read_tum, write_tum
from mcgs_warp.eval.plots import MAPPING_SIZE, TRAJECTORY_SIZE, plot_mapping, plot_trajectory
from mcgs_warp.eval.trajectory import evaluate
from mcgs_warp.io import read_image


def circle(n=30, noise=0.0, seed=0):
    t = np.linspace(0.0, 3.0, n)
    xyz = np.stack([np.cos(t), np.sin(t), 0.1 * t], 1)
    return t, xyz + np.random.default_rng(seed).normal(0.0, noise, xyz.shape)


def has_error_colorbar(fig):
    return any(ax.get_ylabel() == "position error [cm]" for ax in fig.axes[1:])


def assert_png(path, size):
    assert path.read_bytes().startswith(b"\x89PNG")
    img = read_image(path)
    assert (img.shape[1], img.shape[0]) == size
    assert img.std() > 0.05  # something is drawn
    assert not list(path.parent.glob("*.tmp"))


def test_trajectory_plot_with_ground_truth(tmp_path):
    t, gt = circle()
    _, est = circle(noise=0.01)
    path = tmp_path / "plots" / "trajectory.png"
    fig = plot_trajectory(path, est, gt, t)
    assert_png(path, TRAJECTORY_SIZE)
    top = fig.axes[0]
    labels = [x.get_text() for x in top.get_legend().get_texts()]
    assert "ground truth" in labels and any(s.startswith("estimate") for s in labels)
    assert has_error_colorbar(fig)
    assert top.get_aspect() == 1.0  # equal axes
    errors = [ax for ax in fig.axes if ax.get_ylabel() == "translation error [cm]"]
    assert len(errors) == 1 and errors[0].get_xlabel() == "time [s]"


def test_trajectory_plot_without_ground_truth(tmp_path):
    _, est = circle()
    path = tmp_path / "trajectory.png"
    fig = plot_trajectory(path, est)
    assert_png(path, (TRAJECTORY_SIZE[1] + 120, TRAJECTORY_SIZE[1]))
    assert fig.axes[0].get_legend() is not None
    assert not has_error_colorbar(fig)


def test_mapping_plot(tmp_path):
    it = np.arange(200)
    loss = 0.05 * np.exp(-it / 80) + 0.01
    psnr = 20 + 8 * (1 - np.exp(-it / 60)) + np.random.default_rng(0).normal(0, 0.5, 200)
    path = tmp_path / "mapping.png"
    fig = plot_mapping(path, it, loss, psnr)
    assert_png(path, MAPPING_SIZE)
    assert [ax.get_ylabel() for ax in fig.axes] == ["loss", "PSNR [dB]"]
    assert all(ax.get_legend() is not None for ax in fig.axes)


def test_eval_plot_is_the_run_figure(tmp_path):
    t, gt = circle(40)
    _, est = circle(40, noise=0.02)
    poses = np.tile(np.eye(4), (40, 1, 1))
    G, E = poses.copy(), poses.copy()
    G[:, :3, 3], E[:, :3, 3] = gt, est
    write_tum(tmp_path / "gt.txt", Trajectory(t, G))
    write_tum(tmp_path / "est.txt", Trajectory(t[::2], E[::2]))
    out = tmp_path / "eval.png"
    assert main(["eval", "--est", str(tmp_path / "est.txt"), "--gt", str(tmp_path / "gt.txt"), "--plot", str(out)]) == 0
    assert_png(out, TRAJECTORY_SIZE)
    m, aligned, matched, times = evaluate(read_tum(tmp_path / "est.txt"), read_tum(tmp_path / "gt.txt"), return_timestamps=True)
    assert len(times) == len(aligned) == len(matched) == m.n_matched == 20
    np.testing.assert_allclose(times, t[::2], atol=1e-6)
    plot_trajectory(tmp_path / "run.png", aligned, matched, times)  # what write_outputs draws
    np.testing.assert_array_equal(read_image(out), read_image(tmp_path / "run.png"))


def test_plots_leave_pyplot_alone(tmp_path):
    code = (
        "import sys, numpy as np; from mcgs_warp.eval.plots import plot_trajectory; "
        f"plot_trajectory({str(tmp_path / 'p.png')!r}, np.random.rand(5, 3), np.random.rand(5, 3)); "
        "sys.exit('pyplot imported' if 'matplotlib.pyplot' in sys.modules else 0)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_top_view_is_the_plane_of_the_motion():
    from mcgs_warp.eval.plots import trajectory_figure, view_plane

    # a KITTI-like drive: camera axes (x right, y down, z forward), a turn in the x-z plane, a little bump in y
    t = np.linspace(0.0, 1.5, 40)
    xyz = np.stack([20 * (1 - np.cos(t)), 0.3 * np.sin(5 * t), 20 * np.sin(t)], 1)
    for gravity in ([0.0, 1.0, 0.0], None):
        P = view_plane(xyz, gravity)
        np.testing.assert_allclose(P.T @ P, np.eye(2), atol=1e-12)
        assert abs(P[1, 0]) < 0.1 and abs(P[1, 1]) < 0.1  # y (gravity) is hardly drawn
    P = view_plane(xyz, [0.0, 1.0, 0.0])
    np.testing.assert_allclose(P[1], 0.0, atol=1e-12)  # exactly orthogonal to gravity
    # looking down against gravity: the drawn axes and "up" (-y) are right-handed
    assert np.cross(P[:, 0], P[:, 1]) @ np.array([0.0, -1.0, 0.0]) == pytest.approx(1.0)
    fig = trajectory_figure(xyz + 0.01, xyz, t, gravity=[0.0, 1.0, 0.0], ate_label="SE(3) ATE")
    x, y = fig.axes[0].lines[0].get_data()  # the ground-truth line in view coordinates
    assert np.ptp(x) > 10 and np.ptp(y) > 5  # the turn, not a side view (the old x-y plane spans 0.6 m in y)
    assert fig.get_suptitle().startswith("SE(3) ATE 1.73 cm")
