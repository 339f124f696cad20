"""Tracking settings that were constants: each reaches the stage that uses it, and the
config loader bounds it."""

import pytest

from mcgs_warp.errors import InputError
from mcgs_warp.system.config import load_run_config
from mcgs_warp.system.slam import SLAM


def _config(tmp_path, text):
    path = tmp_path / "run.yaml"
    path.write_text(text)
    return load_run_config(path)


def test_defaults_are_the_former_constants(synthetic_seq):
    slam = SLAM(synthetic_seq, load_run_config())
    t = slam.tracker
    assert slam.buf.scale_grid == (4, 6) and t.mcba.cfg.lm_lambda == 1e-4
    assert (t.guided.settled_px, t.guided.settled_outliers, t.guided.photo_sigma, t.guided_or_raw.min_confident) == (0.25, 0.05, 0.02, 0.25)


def test_settings_reach_their_stages(synthetic_seq, tmp_path):
    cfg = _config(tmp_path, "tracking:\n  lm_lambda: 0.01\n  jdsa_rows: 2\n  jdsa_cols: 3\n  flow:\n    settled_px: 0.5\n    settled_outliers: 0.1\n    photo_sigma: 0.04\n    min_confident: 0.3\n")
    slam = SLAM(synthetic_seq, cfg)
    t = slam.tracker
    assert slam.buf.scale_grid == (2, 3) and slam.buf.scales.shape[1:] == (len(synthetic_seq.rig), 2, 3)  # each keyframe's JDSA grid
    assert t.mcba.cfg.lm_lambda == 0.01
    assert (t.guided.settled_px, t.guided.settled_outliers, t.guided.photo_sigma, t.guided_or_raw.min_confident) == (0.5, 0.1, 0.04, 0.3)


@pytest.mark.parametrize("text, key", [("tracking:\n  lm_lambda: 0\n", "lm_lambda"), ("tracking:\n  jdsa_rows: 0\n", "jdsa_rows"), ("tracking:\n  flow:\n    settled_outliers: 1.5\n", "settled_outliers"), ("tracking:\n  flow:\n    photo_sigma: 0\n", "photo_sigma")])
def test_values_that_break_a_stage_are_refused(tmp_path, text, key):
    with pytest.raises(InputError, match=key):
        _config(tmp_path, text)


def test_refinement_takes_at_most_its_steps_per_keyframe(synthetic_seq, tmp_path, monkeypatch):
    """Joint refinement: ``refinement.iterations`` steps, at most ``steps_per_keyframe`` per
    registered keyframe (one step renders one keyframe's cameras): DDAD's 2 keyframes take 120
    steps, not 360; 0 lifts the limit."""
    import mcgs_warp.system.slam as slam_module

    steps = []
    monkeypatch.setattr(slam_module, "joint_refinement", lambda mapper, n, **kw: steps.append(n))
    for text, registered, expected in (("", 2, 120), ("", 7, 360), ("refinement:\n  steps_per_keyframe: 0\n", 2, 360), ("refinement:\n  steps_per_keyframe: 10\n  iterations: 50\n", 3, 30)):
        slam = SLAM(synthetic_seq, _config(tmp_path, text or "{}\n"))
        slam.buf.targets.update({k: None for k in range(registered)})  # registered keyframes (the count is what matters)
        slam.refine()
        assert steps[-1] == expected, (text, registered, steps)
    with pytest.raises(InputError, match="steps_per_keyframe"):
        _config(tmp_path, "refinement:\n  steps_per_keyframe: -1\n")
