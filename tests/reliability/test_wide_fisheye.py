"""A rig of two TUM-VI-like fisheyes (195 degrees): their image corners lie beyond 90 degrees
off the axis, where the model has no ray (camera_unproject gives NaN). Those pixels must drop
out of every stage, even where a stage is handed a depth and a confident match for them."""

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "ba"))

from problems import Problem  # noqa: E402

from mcgs_warp.ba.mcba import MCBA, MCBAConfig  # noqa: E402
from mcgs_warp.data.synthetic import SceneRenderer, build_scene, rig_trajectory  # noqa: E402
from mcgs_warp.kernels.sweep import camera_rays  # noqa: E402
from mcgs_warp.mapping.mapper import Mapper, MappingConfig  # noqa: E402
from mcgs_warp.rig import rig_from_dict  # noqa: E402

FRAMES = (0, 2, 4)


def wide_rig():
    fish = dict(model="fisheye", resolution=[128, 128], intrinsics=[48.0, 48.0, 63.5, 63.5], distortion=[0.0034, 0.0007, -0.0017, 0.0003])
    forward = [-0.5, 0.5, -0.5, 0.5]  # optical axis along the body's x
    return rig_from_dict({"cameras": [dict(name=n, **fish, T_b_c=dict(translation=[0.25, y, 0.0], quaternion=forward)) for n, y in (("left", 0.15), ("right", -0.15))]})


class Frames(SimpleNamespace):
    """What tests/ba/problems.Problem reads of a sequence: rig, groundtruth, frames by index."""

    def __init__(self, rig, groundtruth, frames):
        super().__init__(rig=rig, groundtruth=groundtruth, frames=frames)

    def __getitem__(self, k):
        return self.frames[k]


@pytest.fixture(scope="module")
def wide():
    """Images and exact depths of the two fisheyes at three poses, and their no-ray masks."""
    rig = wide_rig()
    traj = rig_trajectory(max(FRAMES) + 1)
    renderer = SceneRenderer(build_scene(0), rig)
    frames = []
    for k in FRAMES:
        colour, depth = renderer.render(traj.poses[k])
        frames.append(SimpleNamespace(images=list(colour), depths=list(depth), timestamp=0.1 * k))
    no_ray = [~np.isfinite(camera_rays(s.warp_camera(), "cpu").numpy()).all(-1) for s in rig.cameras]
    return Frames(rig, SimpleNamespace(poses=traj.poses[list(FRAMES)]), frames), no_ray


def test_ray_caster_sees_nothing_without_a_ray(wide):
    from scipy.ndimage import binary_erosion

    seq, no_ray = wide
    for c, mask in enumerate(no_ray):
        assert 0.04 < mask.mean() < 0.10  # the corners
        inner = binary_erosion(mask)  # colour is supersampled: next to the circle part of a pixel sees
        for f in seq.frames:
            assert np.isfinite(f.images[c]).all() and np.isfinite(f.depths[c]).all()
            assert (f.depths[c][mask] == 0).all() and (f.images[c][inner] == 0).all()
            assert (f.depths[c][~mask] > 0).mean() > 0.99


def test_mcba_drops_pixels_without_a_ray(wide):
    """A depth and a confident (wrong) match on every no-ray grid pixel change nothing: from
    a perturbed start MCBA recovers the true poses and depths."""
    seq, no_ray = wide
    P = Problem(seq, range(len(FRAMES)), stride=4)
    grid_no_ray = ~np.isfinite(P.buf.rays.numpy()).all(-1)  # [C,h,w]: MCBA's grid pixels without a ray
    assert grid_no_ray.any(axis=(1, 2)).all()
    targets, weights = P.targets.copy(), P.weights.copy()
    for e, (i, ci, j, cj) in enumerate(P.edges[:, :4]):
        weights[e][grid_no_ray[ci]] = 1.0
        targets[e][grid_no_ray[ci]] = (3.0, 5.0)
    P.true_disp[:, grid_no_ray] = 0.5  # a 2 m start depth there
    P.perturb(np.random.default_rng(0), trans=0.03, rot_deg=1.0, depth_noise=0.05)
    assert P.pose_errors()[:, 0].max() > 0.02
    stats = MCBA(P.buf, MCBAConfig(iterations=10)).solve(P.edges, targets, weights)
    assert stats.accepted > 0 and np.isfinite(stats.cost).all()
    err = P.pose_errors()
    assert err[:, 0].max() < 1e-3 and err[:, 1].max() < 0.02, err


def test_mapping_skips_pixels_without_a_ray(wide):
    """Depth targets on no-ray pixels (as a prior would give) seed no Gaussian and give no
    depth or normal term; the loss and its gradients stay finite."""
    seq, no_ray = wide
    P = Problem(seq, range(len(FRAMES)), stride=4)
    m = Mapper(P.buf, config=MappingConfig(densify_every=0))
    stride = m.cfg.insert_stride
    depths = [np.where(mask, 2.0, d).astype(np.float32) for d, mask in zip(seq.frames[0].depths, no_ray)]
    added = m.add_keyframe(0, depths)
    o = stride // 2
    expected = sum(int(((d[o::stride, o::stride] > 0) & (d[o::stride, o::stride] < 50.0) & ~mask[o::stride, o::stride]).sum()) for d, mask in zip(depths, no_ray))
    assert added == expected
    assert all(np.isfinite(v).all() for v in m.map.to_numpy().values())
    targets = m.loss.targets(0, P.buf.images[0], depths)
    assert (targets.depth.numpy()[np.stack(no_ray)] == 0).all()
    for _ in range(3):
        r = m.step(0)
        assert np.isfinite(r.loss) and m.rejected_steps == 0
    assert all(np.isfinite(v).all() for v in m.map.to_numpy().values())
