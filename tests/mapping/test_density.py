"""The view rules of the density control (Mapper.densify_and_prune): screen size, floaters,
and the opacity reset. Each test fails with its rule switched off."""

import numpy as np

from conftest import KEYFRAMES, make_mapper
from mcgs_warp.mapping.mapper import MappingConfig


def test_screen_size_rule_prunes_gaussians_wider_than_the_budget(fitted, mapping_seq):
    pruned = {}
    for share in (0.0, 0.25):
        m = make_mapper(mapping_seq, MappingConfig(densify_every=0, prune_screen=share, prune_scale=100.0), fitted)
        d = m.map.to_numpy()
        d["log_scales"][:5] = np.log(1.5)  # 1.5 m sigma a few metres away: wider than a quarter of the image
        m.map.set_numpy(d)
        m.map.set_statistics(np.zeros(len(d["means"])), np.ones(len(d["means"])))
        radius, _, _ = m.view_statistics()
        width = max(s.width for s in m.buf.rig.cameras)
        assert (radius[:5] > 0.25 * width).all()
        rep = m.densify_and_prune()
        pruned[share] = (rep.oversized_on_screen, int((radius[5:] > 0.25 * width).sum()))
    assert pruned[0.0][0] == 0
    assert pruned[0.25][0] == 5 + pruned[0.25][1] and pruned[0.25][1] < 5, pruned


def test_floater_rule_prunes_what_keyframes_see_in_front_of_their_depth(fitted, mapping_seq):
    """Copies of 30 surface Gaussians pulled halfway to the camera that seeded them are seen
    in front of the exact depth by the keyframes; they are pruned, the surface is not."""
    base = make_mapper(mapping_seq, MappingConfig(densify_every=0), fitted)
    d = base.map.to_numpy()
    n = len(d["means"])
    cam = base.buf.rig.camera_poses(base.buf.get_poses()[0])[0][:3, 3]
    radius, front, agree = base.view_statistics()
    pick = np.nonzero((agree >= 3) & (front == 0))[0][:30]  # well-seen surface Gaussians
    assert len(pick) == 30
    floaters = {k: v[pick].copy() for k, v in d.items()}
    floaters["means"] = 0.5 * (floaters["means"] + cam)
    both = {k: np.concatenate([d[k], floaters[k]]) for k in d}
    for rule in (False, True):
        m = make_mapper(mapping_seq, MappingConfig(densify_every=0, prune_floaters=rule, densify_grad=1e9), both)
        m.map.set_statistics(np.zeros(n + 30), np.ones(n + 30))
        rep = m.densify_and_prune()
        if not rule:
            assert rep.floaters == 0 and len(m.map) >= n + 30 - 10
        else:
            assert rep.floaters >= 30 and rep.floaters < 30 + 0.02 * n, rep
            assert len(m.map) > 0.97 * n


def test_opacity_reset_clamps_opacities_and_their_moments(fitted, mapping_seq):
    m = make_mapper(mapping_seq, MappingConfig(densify_every=0, opacity_reset_every=3), fitted)
    m.optimize(2, keyframes=[0])
    assert (1 / (1 + np.exp(-m.map.to_numpy()["opacity_logits"])) > 0.5).mean() > 0.5
    m.step(0)  # the third step resets
    p = 1 / (1 + np.exp(-m.map.to_numpy()["opacity_logits"]))
    assert p.max() <= 2 * m.cfg.prune_opacity + 1e-6
    mo, v, _ = m.adam.state["opacity_logits"]
    assert not mo.numpy().any() and not v.numpy().any()
    m.cfg.opacity_reset_every = 0
    m.optimize(60, keyframes=list(range(len(KEYFRAMES))))  # what the views need comes back (slowly: logit steps of lr_opacity)
    assert (1 / (1 + np.exp(-m.map.to_numpy()["opacity_logits"])) > 0.1).mean() > 0.2
