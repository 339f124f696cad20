"""Checkpoint and resume: an interrupted run, resumed, ends exactly where an
uninterrupted one does."""

import json
import shutil

import numpy as np
import pytest
import warp as wp

from mcgs_warp.data.synthetic import generate
from mcgs_warp.data.trajectory import read_tum
from mcgs_warp.errors import InputError
from mcgs_warp.system.run import run_sequence
from run_configs import small_config

pytestmark = pytest.mark.slow  # runs the whole system: `pytest -m "not slow"` leaves it out


def config(keypoint_weight: float = 0.0):
    # stereo.temporal_baseline: keyframes' time-baseline sweeps on this slow drive (the checkpoint carries them)
    return small_config(refinement_iterations=3, keypoint_weight=keypoint_weight, stereo={"temporal_baseline": 0.1})


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """``depth -> (data folder, uninterrupted run's folder, its metrics)``, each made once."""
    made = {}

    def get(depth):
        if depth not in made:
            root = tmp_path_factory.mktemp(f"resume_{depth}")
            generate(root / "data", n_cameras=2, n_frames=7, seed=4, progress=False, depth=depth)
            made[depth] = (root / "data", root / "full", run_sequence(root / "data", root / "full", config(1.0 if depth == "none" else 0.0), progress=False))
        return made[depth]

    return get


@pytest.mark.parametrize("depth, stop", [("exact", 2), ("none", 1), ("none", 4)])
def test_interrupted_then_resumed_run_matches_an_uninterrupted_one(uninterrupted, tmp_path, depth, stop):
    """With exact depth the mapping targets are the sensor's; without depth they are
    MCBA's estimates (and the correspondences were re-estimated along the way), which
    the checkpoint must carry, and so are the keypoint tracks in MCBA (on in that case);
    stopping after keyframe 0 interrupts the bootstrap, before anything was mapped; after
    keyframe 3, the mapped keyframes' sweep depth must come back as it was swept."""
    data, full_out, full = uninterrupted(depth)
    weight = 1.0 if depth == "none" else 0.0
    with pytest.raises(KeyboardInterrupt):
        run_sequence(data, tmp_path / "cut", config(weight), progress=False, stop_after_keyframes=stop)
    assert (tmp_path / "cut" / "checkpoint.npz").is_file()
    assert not (tmp_path / "cut" / "trajectory.txt").exists()  # nothing final before the end
    resumed = run_sequence(data, tmp_path / "cut", config(weight), progress=False, resume=True)
    a = read_tum(full_out / "trajectory.txt")
    b = read_tum(tmp_path / "cut" / "trajectory.txt")
    assert full["n_keyframes"] == resumed["n_keyframes"] >= 3
    atol = 1e-6
    if wp.get_device().is_cuda:
        # CUDA's float atomics (the renderer's adjoint) sum in a varying order, so two
        # uninterrupted runs already differ: the resumed run may differ no more than that.
        run_sequence(data, tmp_path / "again", config(weight), progress=False)
        spread = np.abs(read_tum(tmp_path / "again" / "trajectory.txt").poses - a.poses).max()
        atol = max(atol, 5 * spread)
    np.testing.assert_allclose(b.positions, a.positions, atol=atol)
    np.testing.assert_allclose(b.poses, a.poses, atol=atol)
    assert resumed["n_gaussians"] == full["n_gaussians"]
    assert resumed["depth_source"] == full["depth_source"] == ("sensor" if depth == "exact" else "stereo")
    if depth == "exact" or stop > 1:
        return

    other = config(weight)
    other.mapping.iterations_per_keyframe = 4
    with pytest.raises(InputError, match="another configuration"):
        run_sequence(data, tmp_path / "cut", other, progress=False, resume=True)
    # as many frames, but others (another --frames range): the keyframes' times tell
    shifted = tmp_path / "shifted"
    shutil.copytree(data, shifted)
    stamps = np.loadtxt(shifted / "timestamps.txt", ndmin=2)[:, 0]
    (shifted / "timestamps.txt").write_text("".join(f"{t + 0.05:.6f}\n" for t in stamps))
    with pytest.raises(InputError, match="another configuration or sequence"):
        run_sequence(shifted, tmp_path / "cut", config(weight), progress=False, resume=True)
    # one file per mapped keyframe beside the checkpoint (replaced ones are pruned)
    with np.load(tmp_path / "cut" / "checkpoint.npz") as z:
        names = set(z["keyframe_files"].tolist())
        assert len(names) == len(z["mapped_keys"]) >= 3
    assert {p.name for p in (tmp_path / "cut" / "checkpoint.keyframes").glob("*.npz")} == names
    swept = 0
    for p in (tmp_path / "cut" / "checkpoint.keyframes").glob("*.npz"):
        with np.load(p) as z:
            swept += "sweep_depth_cam0" in z.files
    assert swept >= 3
    # the checkpoint's correspondences live beside it: without them resuming is refused, clearly
    assert any((tmp_path / "cut" / "checkpoint.corr").glob("seg_*.npz"))
    shutil.rmtree(tmp_path / "cut" / "checkpoint.corr")
    with pytest.raises(InputError, match="checkpoint.corr"):
        run_sequence(data, tmp_path / "cut", config(weight), progress=False, resume=True)
    # a checkpoint of an older version is refused by name (one without a format number:
    # before 2026-11-27), and a damaged one names the array it lacks
    ckpt = tmp_path / "cut" / "checkpoint.npz"
    with np.load(ckpt) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    np.savez(ckpt, **dict(arrays, meta=np.array(json.dumps({k: v for k, v in meta.items() if k != "format"}))))
    with pytest.raises(InputError, match="older version \\(format 1"):
        run_sequence(data, tmp_path / "cut", config(weight), progress=False, resume=True)
    np.savez(ckpt, **{k: v for k, v in arrays.items() if k != "exposure"})
    with pytest.raises(InputError, match="no array 'exposure'"):
        run_sequence(data, tmp_path / "cut", config(weight), progress=False, resume=True)


def test_checkpoint_rewrites_only_the_keyframes_that_changed(tmp_path, monkeypatch):
    """Each mapped keyframe's depth targets go to a file named by their content: a second
    checkpoint after one keyframe's targets changed writes that one file, not all of them."""
    from types import SimpleNamespace

    import mcgs_warp.io as io
    from mcgs_warp.rig import CameraSpec, Rig
    from mcgs_warp.system.checkpoint import _save_keyframe_files

    rig = Rig([CameraSpec("a", "pinhole", 8, 6, (5.0, 5.0, 3.5, 2.5)), CameraSpec("b", "pinhole", 4, 4, (3.0, 3.0, 1.5, 1.5))])
    rng = np.random.default_rng(0)
    fake = SimpleNamespace(tracker=SimpleNamespace(exact_depth=False, depth_targets=SimpleNamespace(sweeps={})), seq=SimpleNamespace(rig=rig), buf=SimpleNamespace(targets={}), mapper=SimpleNamespace(placed={}))
    for k in range(5):
        fake.buf.targets[k] = [rng.random((6, 8)).astype(np.float32), rng.random((4, 4)).astype(np.float32)]
        fake.mapper.placed[k] = rng.random((2, 3, 4))
    written, real = [], io.atomic_write
    monkeypatch.setattr(io, "atomic_write", lambda path, *a, **kw: (written.append(path.name), real(path, *a, **kw))[1])
    first = _save_keyframe_files(fake, tmp_path / "kf")
    assert len(written) == 5 and first == sorted(written)
    fake.buf.targets[3][1] = fake.buf.targets[3][1] + 1
    fake.tracker.depth_targets.sweeps[3] = [rng.random((3, 4)).astype(np.float16), rng.random((2, 2)).astype(np.float16)]
    written.clear()
    second = _save_keyframe_files(fake, tmp_path / "kf")
    assert written == [second[3]] and second[3] != first[3] and second[:3] == first[:3]
    with np.load(tmp_path / "kf" / second[3]) as z:
        np.testing.assert_array_equal(z["targets_cam1"], fake.buf.targets[3][1])
        np.testing.assert_array_equal(z["mapped_depth"], fake.mapper.placed[3])
        np.testing.assert_array_equal(z["sweep_depth_cam1"], fake.tracker.depth_targets.sweeps[3][1])
