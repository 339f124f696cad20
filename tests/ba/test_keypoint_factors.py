"""Keypoint factors inside MCBA: Jacobians against finite differences (pinhole, fisheye and
equirectangular cameras), and an MCBA solve whose dense correspondences carry no weight
recovering perturbed poses from keypoint tracks alone."""

import numpy as np

from mcgs_warp.ba.keypoint_factors import KeypointFactors, KeypointProblem
from mcgs_warp.ba.mcba import MCBA, MCBAConfig
from mcgs_warp.ba.edges import unproject_pixels
from mcgs_warp.geometry import se3_exp
from problems import Problem
from test_keypoints import mixed_rig


def tracks(rig, poses, n_tracks, rng, noise_px=0.0):
    """Random tracks seen from slot 0's views and observed in every slot/camera that sees them."""
    src_slot, src_cam, rays, disp = [], [], [], []
    o_t, o_s, o_c, o_uv = [], [], [], []
    from mcgs_warp.kernels import reference

    for t in range(n_tracks):
        s0 = int(rng.integers(len(poses)))
        c0 = int(rng.integers(len(rig)))
        spec = rig.cameras[c0]
        uv = rng.uniform([5, 5], [spec.width - 5, spec.height - 5])
        ray = unproject_pixels(spec.warp_camera(), uv[None])[0]
        z = rng.uniform(2.0, 15.0)
        T_w_c = poses[s0] @ spec.T_b_c
        X_w = T_w_c[:3, :3] @ (ray * z) + T_w_c[:3, 3]
        seen = []
        for s, T in enumerate(poses):
            for c, cs in enumerate(rig.cameras):
                if (s, c) == (s0, c0):
                    continue
                T_c_w = np.linalg.inv(T @ cs.T_b_c)
                X = T_c_w[:3, :3] @ X_w + T_c_w[:3, 3]
                cam = cs.warp_camera()
                if not reference.in_domain(cam, X[None])[0]:
                    continue
                p = reference.project(cam, X[None])[0]
                if 0 <= p[0] < cs.width and 0 <= p[1] < cs.height:
                    seen.append((s, c, p + rng.normal(0, noise_px, 2)))
        if not seen:
            continue
        for s, c, p in seen:
            o_t.append(len(src_slot))
            o_s.append(s)
            o_c.append(c)
            o_uv.append(p)
        src_slot.append(s0)
        src_cam.append(c0)
        rays.append(ray)
        disp.append(1.0 / z)
    return KeypointProblem(np.array(src_slot), np.array(src_cam), np.array(rays), np.array(disp), np.array(o_t), np.array(o_s), np.array(o_c), np.array(o_uv), np.ones(len(o_t)))


def test_keypoint_factor_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    rig = mixed_rig()
    poses = np.stack([np.eye(4), se3_exp(np.array([0.4, 0.1, 0.0, 0.0, 0.0, 0.3])), se3_exp(np.array([0.8, -0.2, 0.1, 0.05, 0.0, 0.6]))])
    prob = tracks(rig, poses, 40, rng)
    f = KeypointFactors(prob, rig, stride=8, huber_delta=1.0, min_disp=0.01)
    e, J_i, J_j, J_d, valid = f.jacobians(poses)
    assert valid.all() and len(prob) > 40
    assert {prob.src_cam[t] for t in prob.obs_track} | set(prob.obs_cam.tolist()) == set(range(len(rig)))  # every camera model takes part
    eps = 1e-6
    for slot_of, J in (("src", J_i), ("obs", J_j)):
        for k in range(6):
            d = np.zeros(6)
            d[k] = eps
            num = np.zeros_like(e)
            for sign in (1, -1):
                # move each slot in turn; an observation's residual changes through its own slots only
                r_all = []
                for s in range(len(poses)):
                    P = poses.copy()
                    P[s] = P[s] @ se3_exp(sign * d)
                    r_all.append(f.residuals(P, f.disp)[0])
                slots = prob.src_slot[prob.obs_track] if slot_of == "src" else prob.obs_slot
                other = prob.obs_slot if slot_of == "src" else prob.src_slot[prob.obs_track]
                r = np.stack(r_all)[slots, np.arange(len(prob))]
                num += sign * r
            num /= 2 * eps
            only = slots != other  # where both ends are one slot the two Jacobians add up
            np.testing.assert_allclose(J[only, :, k], num[only], atol=2e-5, rtol=1e-4)
    dd = 1e-7
    num = (f.residuals(poses, f.disp + dd)[0] - f.residuals(poses, f.disp - dd)[0]) / (2 * dd)
    np.testing.assert_allclose(J_d, num, atol=2e-4, rtol=1e-4)


def test_mcba_recovers_poses_from_keypoint_tracks_alone(synthetic_seq):
    """The dense correspondences get zero weight: only the keypoint tracks (0.3 px of noise,
    depths 20 % off) can move the poses back to the truth."""
    rng = np.random.default_rng(4)
    P = Problem(synthetic_seq, [0, 2, 4, 6], cross_view=False)
    prob = tracks(synthetic_seq.rig, P.true_poses, 150, rng, noise_px=0.3)
    prob.disp *= np.exp(0.2 * rng.normal(size=len(prob.disp)))
    P.perturb(rng, trans=0.05, rot_deg=1.0)
    before = P.pose_errors()[1:, 0].max()
    mcba = MCBA(P.buf, MCBAConfig(iterations=10, huber_delta=0.5))
    stats = mcba.solve(P.edges, P.targets, np.zeros_like(P.weights), keyframes=[0, 1, 2, 3], keypoints=prob)
    err = P.pose_errors()[1:]
    assert stats.accepted > 0
    assert before > 0.04 and err[:, 0].max() < 0.005 and err[:, 1].max() < 0.05, (before, err)
