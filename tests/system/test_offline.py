"""The offline photo-consistency pass: which views judge a depth target (source selection)."""

from types import SimpleNamespace

import numpy as np
from mcgs_warp.kernels.camera import make_camera
from mcgs_warp.kernels.sweep import camera_rays
from mcgs_warp.system.offline import photo_consistent_targets, source_scores


def _cam():
    return make_camera("pinhole", 64, 48, (50.0, 50.0, 31.5, 23.5))


def _T_src_ref(centre, yaw_deg=0.0):
    """T_src_ref of a source at ``centre`` (reference frame), turned ``yaw_deg`` about y."""
    a = np.radians(yaw_deg)
    R_ref_src = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    T = np.eye(4)
    T[:3, :3] = R_ref_src.T
    T[:3, 3] = -R_ref_src.T @ np.asarray(centre, float)
    return T


def test_scores_prefer_parallax_near_five_degrees_over_shared_points():
    cam = _cam()
    rays = camera_rays(cam, "cpu").numpy()
    depth = np.full((48, 64), 10.0, np.float32)  # a wall 10 m ahead
    five = 10.0 * np.tan(np.radians(5.0))
    T = np.stack([
        _T_src_ref([0.0, 0.0, 0.0], 2.0),  # the same centre: no parallax
        _T_src_ref([five, 0.0, 0.0]),  # 5 degrees at the wall's centre
        _T_src_ref([4 * five, 0.0, 0.0]),  # ~19 degrees: weak, but something
        _T_src_ref([five, 0.0, 0.0], 180.0),  # looks away: shares nothing
    ])
    s = source_scores(rays, depth, [cam] * 4, T)
    n = int(np.ceil(48 / 8) * np.ceil(64 / 8))  # points sampled every 8 px
    assert s[1] > 0.6 * n  # most points seen from 3-5 degrees (oblique ones from less)
    assert 0.1 * n < s[2] < 0.6 * s[1]
    assert s[0] < 1e-3 * n and s[3] == 0.0
    assert list(np.argsort(-s))[:2] == [1, 2]
    # no depth: nothing to judge with
    assert np.all(source_scores(rays, np.zeros_like(depth), [cam] * 4, T) == 0.0)


def test_the_pass_matches_each_view_against_its_best_sources_only(monkeypatch):
    cam = _cam()
    five = 10.0 * np.tan(np.radians(5.0))
    spec = SimpleNamespace(T_b_c=np.eye(4), warp_camera=lambda: cam)
    # one camera moving sideways: keyframe k at x = k * five / 2; keyframe 2 judged by 0, 1, 3, 4
    poses = np.stack([np.eye(4)] * 5)
    poses[:, 0, 3] = np.arange(5) * five / 2
    depth = np.full((48, 64), 10.0, np.float32)
    grey = np.zeros((48, 64, 3), np.float32)

    class Rig(SimpleNamespace):
        def __len__(self):
            return len(self.cameras)

    class Buffer(SimpleNamespace):
        def __len__(self):
            return len(poses)

    buf = Buffer(
        rig=Rig(cameras=[spec]), get_poses=lambda: poses, full_rays=camera_rays(cam, "cpu").reshape((1, 48, 64)),
        image=lambda k, c: grey, targets={k: [depth] for k in range(5)}, device="cpu",
    )
    seen = {}

    def fake_propagate(ref, rays, d, srcs, cams, T_src_ref, ref_colour=None, device=None):
        centres = np.linalg.inv(T_src_ref)[:, 0, 3]  # source centres in the reference frame
        seen[len(seen)] = np.round(centres / (five / 2)).astype(int).tolist()
        return d

    monkeypatch.setattr("mcgs_warp.kernels.propagation.propagate_depth", fake_propagate)
    photo_consistent_targets(buf, [], [2], radius=2, sources=1)
    assert seen == {0: [-2]} or seen == {0: [2]}  # 5 degrees away: two keyframes, not the next one
    seen.clear()
    photo_consistent_targets(buf, [], [2], radius=2, sources=0)
    assert seen == {0: [-2, -1, 1, 2]}  # 0: every view within the radius
