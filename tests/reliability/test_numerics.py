"""Numerical safety: NaN/Inf inputs never reach the map or the poses."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "ba"))

from problems import Problem  # noqa: E402

from mcgs_warp.ba.mcba import MCBA, MCBAConfig  # noqa: E402
from mcgs_warp.data.synthetic import generate  # noqa: E402
from mcgs_warp.mapping.mapper import Mapper, MappingConfig  # noqa: E402


def test_nan_image_is_rejected(tmp_path, caplog):
    seq = generate(tmp_path / "seq", n_cameras=2, n_frames=3, seed=1, progress=False)
    P = Problem(seq, [0, 2])
    m = Mapper(P.buf, config=MappingConfig(densify_every=0))
    for k, f in enumerate([0, 2]):
        m.add_keyframe(k, seq[f].depths)
    before = m.map.to_numpy()
    P.buf.images[1][0] = P.buf.image(1, 0).copy()
    P.buf.images[1][0][10:20, 10:20] = np.nan  # a corrupted image
    with caplog.at_level("WARNING"):
        r = m.step(1)
    assert np.isnan(r.loss) and m.rejected_steps == 1 and "non-finite" in caplog.text
    after = m.map.to_numpy()
    for key in before:
        np.testing.assert_array_equal(before[key], after[key])
    m.step(0)  # a healthy keyframe still trains
    assert all(np.isfinite(v).all() for v in m.map.to_numpy().values())


def test_nan_correspondences_get_zero_weight(tmp_path):
    """NaN/Inf targets or weights on some pixels of some edges drop those residuals only:
    from a perturbed start MCBA still converges to the truth (the steps are not thrown away)."""
    seq = generate(tmp_path / "seq", n_cameras=2, n_frames=5, seed=1, progress=False)
    P = Problem(seq, [0, 2, 4])
    P.perturb(np.random.default_rng(3), trans=0.05, rot_deg=2.0, depth_noise=0.1)
    assert P.pose_errors()[:, 0].max() > 0.04
    targets, weights = P.targets.copy(), P.weights.copy()
    valid = weights > 0
    assert valid.sum() > 1000
    bad = np.zeros_like(valid)
    bad[0, 2:12] = True  # a band of rows of the first edge ...
    bad[len(bad) // 2, :, 5:15] = True  # ... and of columns of another one
    bad &= valid
    assert bad.sum() > 50 and bad.any(axis=(1, 2)).sum() == 2  # NaNs on two edges only
    targets[bad & (np.arange(bad.shape[2]) % 2 == 0)] = np.nan  # NaN targets, x or y
    targets[bad & (np.arange(bad.shape[2]) % 4 == 1), 1] = np.inf
    weights[bad & (np.arange(bad.shape[2]) % 4 == 3)] = np.nan  # NaN and Inf weights
    weights[bad & (np.arange(bad.shape[2]) % 4 == 1)] = np.inf
    stats = MCBA(P.buf, MCBAConfig(iterations=10)).solve(P.edges, targets, weights)
    assert stats.accepted > 0 and np.isfinite(stats.cost).all()
    assert np.isfinite(P.buf.get_poses()).all() and np.isfinite(P.buf.disp.numpy()).all()
    err = P.pose_errors()
    assert err[:, 0].max() < 1e-3 and err[:, 1].max() < 0.01, err
    assert np.median(P.depth_rel_errors()) < 1e-3


def test_textureless_frames_and_zero_flow(tmp_path):
    """Flat grey frames while the rig moves 5 cm per frame: nothing can be tracked. No
    crash, no keyframes beyond the first and last, finite outputs, and the last keyframe's
    solve is reported as a tracking failure (no confident correspondence) instead of a
    success at the wrong place."""
    from mcgs_warp.data import FolderSequence, FolderWriter, Trajectory
    from mcgs_warp.geometry import pose
    from mcgs_warp.rig import CameraSpec, Rig
    from mcgs_warp.system.run import run_sequence
    from run_configs import small_config

    rig = Rig([CameraSpec("a", "pinhole", 64, 48, (50.0, 50.0, 31.5, 23.5))])
    w = FolderWriter(tmp_path / "flat", rig)
    for k in range(4):
        w.write_frame(k, [np.full((48, 64, 3), 0.5)], [np.full((48, 64), 2.0)])
    moving = np.stack([np.zeros(4), np.zeros(4), 0.05 * np.arange(4)], 1)  # along the optical axis
    w.finish(np.arange(4) * 0.1, Trajectory(np.arange(4) * 0.1, pose(moving, np.tile([0, 0, 0, 1.0], (4, 1)))))
    cfg = small_config(mcba_iterations=None, mapping_iterations=2, global_ba_iterations=None, refinement_iterations=2, renders=1)
    m = run_sequence(FolderSequence(tmp_path / "flat").root, tmp_path / "out", cfg, progress=False)
    assert m["n_keyframes"] == 2 and np.isfinite(m["psnr_db"])
    assert m["tracking_failure_frames"] == [3], m["tracking_failure_frames"]
    assert m["confident_fraction"]["min"] == 0.0
    from mcgs_warp.data.trajectory import read_tum

    assert np.isfinite(read_tum(tmp_path / "out" / "trajectory.txt").poses).all()
