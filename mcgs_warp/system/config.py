"""Run configuration: YAML sections mapped onto dataclasses, every key validated.

Defaults live here and in ``configs/*.yaml`` (one place each: the YAML files only
override what they name)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from ..mapping.mapper import MappingConfig


@dataclass
class TrackingConfig:
    stride: int = 8
    window: int = 8
    keyframe_flow_px: float = 10.0
    temporal_radius: int = 2
    cross_view: bool = True
    mcba_iterations: int = 6
    huber_px: float = 0.1
    prior_weight: float = 1.0
    jdsa: bool = True
    jdsa_rounds: int = 2


@dataclass
class MappingRunConfig(MappingConfig):
    iterations_per_keyframe: int = 15


@dataclass
class RefinementConfig:
    global_ba_iterations: int = 4
    iterations: int = 120
    poses: bool = True
    exposure: bool = True


@dataclass
class OutputConfig:
    renders: int = 4


@dataclass
class RunConfig:
    seed: int = 0
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingRunConfig = field(default_factory=MappingRunConfig)
    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _fill(cls, data, src, prefix):
    if data is None:
        return cls()
    if not isinstance(data, dict):
        raise InputError(src, prefix, f"expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        name = f"{prefix}.{key}" if prefix else str(key)
        if key not in fields:
            raise InputError(src, name, f"unknown key (expected one of {', '.join(sorted(fields))})")
        f = fields[key]
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if dataclasses.is_dataclass(default):
            kwargs[key] = _fill(type(default), value, src, name)
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise InputError(src, name, f"expected true or false, got {value!r}")
            kwargs[key] = value
        elif isinstance(default, int):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise InputError(src, name, f"expected a non-negative integer, got {value!r}")
            kwargs[key] = value
        elif isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value or value < 0:
                raise InputError(src, name, f"expected a non-negative number, got {value!r}")
            kwargs[key] = float(value)
        else:
            kwargs[key] = value
    return cls(**kwargs)


def load_run_config(path=None) -> RunConfig:
    """Read a run configuration (``None``: the packaged ``configs/default.yaml``)."""
    from importlib import resources

    from ..rig import load_yaml

    if path is None:
        path = resources.files("mcgs_warp.configs") / "default.yaml"
    data = load_yaml(Path(str(path)))
    return _fill(RunConfig, data if data is not None else {}, path, "")


def packaged_config(name: str) -> Path:
    from importlib import resources

    return Path(str(resources.files("mcgs_warp.configs") / name))
