"""The small run configuration that the system and reliability tests run: one builder, each
test's own settings as its keywords."""

from __future__ import annotations

import dataclasses

from mcgs_warp.system.config import RunConfig


def small_config(mcba_iterations=2, mapping_iterations=3, global_ba_iterations=1, refinement_iterations=4, renders=0, **tracking) -> RunConfig:
    """``RunConfig()`` with few iterations of each stage and no renders: ``mcba_iterations``
    (``tracking``), ``mapping_iterations`` (``mapping.iterations_per_keyframe``),
    ``global_ba_iterations`` and ``refinement_iterations`` (``refinement``), ``renders``
    (``output``); None keeps RunConfig's default. More keywords are ``tracking`` keys, a nested
    section's as a dict: ``small_config(keypoints=False, stereo={"temporal_baseline": 0.1})``."""
    cfg = RunConfig()
    for section, key, value in (
        ("tracking", "mcba_iterations", mcba_iterations),
        ("mapping", "iterations_per_keyframe", mapping_iterations),
        ("refinement", "global_ba_iterations", global_ba_iterations),
        ("refinement", "iterations", refinement_iterations),
        ("output", "renders", renders),
    ):
        if value is not None:
            setattr(getattr(cfg, section), key, value)
    _set(cfg.tracking, tracking, "tracking")
    return cfg


def _set(section, values: dict, name: str) -> None:
    keys = {f.name for f in dataclasses.fields(section)}
    for key, value in values.items():
        if key not in keys:
            raise TypeError(f"{name} has no key {key!r}")  # a misspelt setting must not pass unnoticed
        if isinstance(value, dict):
            _set(getattr(section, key), value, f"{name}.{key}")
        else:
            setattr(section, key, value)
