"""The synthetic generator: output layout, determinism, and exact geometry."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from mcgs_warp.data import FolderSequence
from mcgs_warp.data.synthetic import generate
from mcgs_warp.kernels import reference


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("synth") / "seq", n_cameras=3, n_frames=5, seed=3, progress=False)


def unproject_cv(spec, uv, depth):
    """Camera-frame points of pixels ``uv`` [M,2] with depth (z), inverted with OpenCV."""
    K = np.array([[spec.intrinsics[0], 0, spec.intrinsics[2]], [0, spec.intrinsics[1], spec.intrinsics[3]], [0, 0, 1]])
    pts = uv.reshape(-1, 1, 2).astype(np.float64)
    if spec.model == "fisheye":
        n = cv2.fisheye.undistortPoints(pts, K, np.array(spec.distortion, dtype=np.float64)).reshape(-1, 2)
    else:
        dist = np.array(list(spec.distortion) + [0.0] * (5 - len(spec.distortion)))
        n = cv2.undistortPoints(pts, K, dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)).reshape(-1, 2)
    return np.concatenate([n, np.ones((len(n), 1))], 1) * depth[:, None]


def bilinear(img, uv):
    x, y = uv[:, 0], uv[:, 1]
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    return (
        img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x0 + 1] * fx * (1 - fy) + img[y0 + 1, x0] * (1 - fx) * fy + img[y0 + 1, x0 + 1] * fx * fy
    )


def test_layout_and_ground_truth(seq):
    root = seq.root
    assert sorted(p.name for p in root.iterdir()) == ["cam0", "cam1", "cam2", "groundtruth.txt", "gt", "metadata.yaml", "rig.yaml", "timestamps.txt"]
    for i in range(3):
        assert len(list((root / f"cam{i}" / "rgb").glob("*.png"))) == 5
        assert len(list((root / f"cam{i}" / "depth").glob("*.png"))) == 5
    assert len(seq.groundtruth) == 5 and np.all(np.diff(seq.timestamps) > 0)
    f = seq[0]
    for img, d in zip(f.images, f.depths):
        assert img.shape == (240, 320, 3) and img.std() > 0.05  # textured, not flat
        assert d.min() > 0.3 and d.max() < 40  # closed room: every pixel has depth


@pytest.mark.parametrize("src, dst, dk", [(0, 0, 2), (0, 1, 0), (0, 2, 1), (1, 0, 3)])
def test_depth_reprojects_into_other_views(seq, src, dst, dk):
    """A pixel's 3D point (from its depth) lands in another camera or frame where that
    view's own depth map sees the same surface."""
    rng = np.random.default_rng(src * 10 + dst)
    rig = seq.rig
    a, b = seq[0], seq[dk]
    T_w_a = rig.camera_poses(seq.groundtruth.poses[0])[src]
    T_w_b = rig.camera_poses(seq.groundtruth.poses[dk])[dst]
    spec_a = rig.cameras[src]
    uv = np.stack([rng.integers(0, spec_a.width, 4000), rng.integers(0, spec_a.height, 4000)], 1).astype(float)
    z = a.depths[src][uv[:, 1].astype(int), uv[:, 0].astype(int)].astype(np.float64)
    p_a = unproject_cv(spec_a, uv, z)
    p_w = p_a @ T_w_a[:3, :3].T + T_w_a[:3, 3]
    T_b_w = np.linalg.inv(T_w_b)
    p_b = p_w @ T_b_w[:3, :3].T + T_b_w[:3, 3]
    cam_b = rig.cameras[dst].warp_camera()
    front = p_b[:, 2] > 0.3
    uv_b = reference.project(cam_b, p_b[front])
    inside = (uv_b[:, 0] >= 0) & (uv_b[:, 0] < cam_b.width - 1) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] < cam_b.height - 1)
    assert inside.sum() > 200, "the views should overlap"
    predicted = p_b[front][inside, 2]
    seen = bilinear(b.depths[dst].astype(np.float64), uv_b[inside])
    rel = np.abs(seen - predicted) / predicted
    agree = rel < 0.01  # same surface (the rest: occlusions, depth edges)
    assert agree.mean() > 0.75
    assert np.median(rel) < 2e-3  # millimetre depth quantization and bilinear lookup


def test_deterministic_for_a_seed(tmp_path, seq):
    again = generate(tmp_path / "again", n_cameras=3, n_frames=2, seed=3, progress=False)
    other = generate(tmp_path / "other", n_cameras=3, n_frames=2, seed=4, progress=False)
    for i in range(3):
        name = f"cam{i}/rgb/000001.png"
        assert (again.root / name).read_bytes() == (seq.root / name).read_bytes()
        assert (other.root / name).read_bytes() != (seq.root / name).read_bytes()
    assert (again.root / "rig.yaml").read_text() == (seq.root / "rig.yaml").read_text()


def _render_seed3(device, dz=0.0):
    from mcgs_warp.data.synthetic import SceneRenderer, build_scene, synthetic_rig

    rig = synthetic_rig(3)
    T_w_b = np.eye(4)
    T_w_b[:3, 3] = (2.0, 0.3, 1.2 + dz)
    return SceneRenderer(build_scene(3, device), rig, device=device).render(T_w_b)


def test_colour_does_not_hang_on_the_rounding_of_the_hit_point():
    """The floor's checker cells meet on the floor's own plane (z = 0): the colour must not
    depend on which side of it the rounded hit point falls. Moving the rig by a micrometre
    changes that rounding (as CUDA's fused multiply-add does), and must not change colour
    except at silhouettes, where a pixel's samples cross an object's edge (8 of 230,400
    pixels here); before the hit point was put on the wall's plane, 5 % of the floor's
    samples took the neighbouring cell's colour (5,738 pixels changed)."""
    (c0, d0), (c1, d1) = _render_seed3("cpu"), _render_seed3("cpu", dz=1e-6)
    assert (d0 > 0).all() and np.median(np.abs(d0 - d1)) < 1e-5
    changed = np.abs(c0 - c1).max(-1) > 0.01
    assert changed.mean() < 2e-4, changed.sum()


@pytest.mark.skipif(not __import__("warp").get_cuda_device_count(), reason="needs a CUDA device")
def test_the_same_sequence_on_cpu_and_cuda():
    """`mcgs-slam synth` writes the same images whatever the device: on an H200 the
    floor's checker once came out scrambled, a different sequence from the CPU's."""
    (cc, dc), (cg, dg) = _render_seed3("cpu"), _render_seed3("cuda:0")
    assert np.median(np.abs(dc - dg)) < 1e-5
    changed = np.abs(cc - cg).max(-1) > 0.01  # silhouettes only (rounding of the edge tests)
    assert changed.mean() < 2e-4, changed.sum()


def test_cli_synth(tmp_path):
    out = tmp_path / "cli"
    res = subprocess.run(
        [sys.executable, "-m", "mcgs_warp", "synth", "--out", str(out), "--frames", "3", "--cameras", "2"],
        capture_output=True,
        text=True,
    )
    assert res.returncode == 0, res.stderr
    seq = FolderSequence(out)
    assert len(seq) == 3 and len(seq.rig) == 2
    res = subprocess.run([sys.executable, "-m", "mcgs_warp", "synth", "--out", str(out), "--cameras", "9"], capture_output=True, text=True)
    assert res.returncode == 2 and "--cameras: expected 1 to 4, got 9" in res.stderr and "Traceback" not in res.stderr


def test_depth_modes_write_what_they_say(tmp_path):
    """exact: cam<i>/depth is the exact depth; mono: a smooth 0.8-1.25 rescaling of it
    (plus noise) and metadata.yaml says so; none: no depth folder. Every mode writes the
    exact depth under gt/, which the sequence serves for evaluation only."""
    from mcgs_warp.data import open_sequence

    seqs = {m: generate(tmp_path / m, n_cameras=2, n_frames=2, seed=0, progress=False, depth=m) for m in ("exact", "mono", "none")}
    gt = seqs["exact"].gt_depths(1)
    for m, s in seqs.items():
        np.testing.assert_array_equal(s.gt_depths(1)[0], gt[0])
        assert (s.root / "metadata.yaml").read_text().strip().endswith(f"depth: {m}")
    np.testing.assert_array_equal(seqs["exact"][1].depths[1], gt[1])
    assert seqs["exact"].depth_exact and seqs["exact"].depth_cameras() == [True, True]
    mono = open_sequence(tmp_path / "mono")
    assert not mono.depth_exact and mono.depth_cameras() == [True, True]
    ratio = mono[1].depths[0] / gt[0]
    inner = ratio[20:-20, 20:-20]  # away from blurred depth edges at the border
    assert 0.7 < np.percentile(inner, 5) and np.percentile(inner, 95) < 1.35
    assert np.std(np.log(inner)) > 0.03  # really rescaled, not the exact depth
    none = open_sequence(tmp_path / "none")
    assert none.depth_cameras() == [False, False] and none[1].depths == [None, None]
    assert not (tmp_path / "none" / "cam0" / "depth").exists()


def test_loop_trajectory_closes_and_revisits():
    """``--trajectory loop``: one closed loop; the last pose is one step short of the
    first (a revisit), headings follow the path, and it stays in the obstacle-free lane.
    Every length moves the rig the same distance per frame (so lengths compare like with
    like); 640 frames drive the full 35.5 m loop, 1280 the same loop at half the speed."""
    from mcgs_warp.data.synthetic import LOOP_FULL, LOOP_STEP, loop_trajectory

    for n in (40, 160, 640, 1280):
        T = loop_trajectory(n).poses
        steps = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
        assert np.allclose(steps, steps.mean(), rtol=0.02)  # constant speed
        path = steps.sum() + np.linalg.norm(T[-1, :3, 3] - T[0, :3, 3])
        if n <= 640:
            assert steps.mean() == pytest.approx(LOOP_STEP, rel=0.02)
        assert path == pytest.approx(min(LOOP_FULL, n * LOOP_STEP), rel=0.02)
        gap = np.linalg.norm(T[-1, :2, 3] - T[0, :2, 3])  # (the height's bob is not periodic)
        assert gap < 1.5 * steps.mean()  # back at the start
        assert np.all(np.abs(T[:, 1, 3]) < 1.6) and T[:, 0, 3].min() > -2.0
        heading = T[:-1, :3, 0]  # body x axis
        move = np.diff(T[:, :3, 3], axis=0)
        cos = np.sum(heading * move, 1) / np.linalg.norm(move, axis=1)
        assert cos.min() > 0.9
        assert np.allclose(loop_trajectory(n).poses, T)
    with pytest.raises(ValueError, match="max_step must be > 0"):
        loop_trajectory(40, max_step=0.0)
    full = loop_trajectory(40, max_step=np.inf).poses  # the full loop, keyframe-spaced
    assert np.ptp(full[:, 0, 3]) == pytest.approx(LOOP_FULL / 2 - np.pi * 1.2 + 2 * 1.2, rel=0.05)


def test_generate_checks_a_trajectory_of_your_own(tmp_path):
    """``generate(trajectory=Trajectory)``: its length is the frame count (one pose is too
    few) and its poses must match its timestamps; nothing is written for a bad one."""
    from mcgs_warp.data.trajectory import Trajectory
    from mcgs_warp.errors import InputError

    T = np.repeat(np.eye(4)[None], 3, 0)
    with pytest.raises(ValueError, match=r"3 timestamps but poses of shape \(2, 4, 4\)"):
        generate(tmp_path / "a", trajectory=Trajectory(np.arange(3) / 10.0, T[:2]), progress=False)
    with pytest.raises(InputError, match="at least 2, got 1"):
        generate(tmp_path / "b", trajectory=Trajectory(np.zeros(1), T[:1]), progress=False)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_cli_synth_casts_a_rig_of_your_own(tmp_path):
    """``synth --rig`` casts the room with the cameras of a rig file (here two 195-degree
    fisheyes, whose corners have no ray: black, depth 0) and writes that rig beside them;
    ``--cameras`` with ``--rig`` is a clear error."""
    from mcgs_warp.kernels.sweep import camera_rays
    from mcgs_warp.rig import rig_from_dict, save_rig

    fish = dict(model="fisheye", resolution=[96, 80], intrinsics=[36.0, 36.0, 47.5, 39.5], distortion=[0.0034, 0.0007, -0.0017, 0.0003])
    forward = [-0.5, 0.5, -0.5, 0.5]
    rig = rig_from_dict({"cameras": [dict(name=n, **fish, T_b_c=dict(translation=[0.2, y, 0.0], quaternion=forward)) for n, y in (("a", 0.1), ("b", -0.1))]})
    save_rig(rig, tmp_path / "rig.yaml")
    out = tmp_path / "wide"
    cmd = [sys.executable, "-m", "mcgs_warp", "synth", "--out", str(out), "--frames", "2", "--rig", str(tmp_path / "rig.yaml")]
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    seq = FolderSequence(out)
    assert [c.name for c in seq.rig.cameras] == ["a", "b"] and seq.rig.cameras[1].intrinsics == tuple(fish["intrinsics"])
    no_ray = ~np.isfinite(camera_rays(rig.cameras[0].warp_camera(), "cpu").numpy()).all(-1)
    assert 0.02 < no_ray.mean() < 0.2
    depth = seq.gt_depths(1)[0]
    assert (depth[no_ray] == 0).all() and (depth[~no_ray] > 0).mean() > 0.99
    res = subprocess.run(cmd + ["--cameras", "2"], capture_output=True, text=True)
    assert res.returncode == 2 and "--cameras" in res.stderr and "Traceback" not in res.stderr


def test_a_late_camera_sees_where_the_rig_is_at_its_own_time(tmp_path):
    """``camera_delays``: camera 1 firing one frame period (0.1 s) late sees at frame k what it
    sees undelayed at frame k + 1; camera 0, undelayed, is untouched; the folder still stamps
    synchronized frames. Past the last pose the motion is extrapolated."""
    from mcgs_warp.data.synthetic import FRAME_RATE, pose_at, rig_trajectory

    plain = generate(tmp_path / "plain", n_cameras=2, n_frames=4, progress=False, depth="none")
    late = generate(tmp_path / "late", n_cameras=2, n_frames=4, progress=False, depth="none", camera_delays=[0.0, 1.0 / FRAME_RATE])
    assert np.array_equal(late.timestamps, plain.timestamps)
    for k in range(3):
        assert np.array_equal(late[k].images[0], plain[k].images[0])
        assert np.abs(late[k].images[1] - plain[k + 1].images[1]).mean() < 1e-3, k
        assert np.abs(late[k].images[1] - plain[k].images[1]).mean() > 1e-2, k  # the rig moved in between
    traj = rig_trajectory(4)
    step = traj.poses[3][:3, 3] - traj.poses[2][:3, 3]
    assert np.allclose(pose_at(traj, traj.timestamps[3] + 0.05)[:3, 3], traj.poses[3][:3, 3] + 0.5 * step)
    with pytest.raises(ValueError, match="camera_delays"):
        generate(tmp_path / "bad", n_cameras=2, n_frames=2, progress=False, camera_delays=[0.0])
