"""Run configuration: YAML sections mapped onto dataclasses, every key validated.

The defaults live here, one line each with its meaning and unit; the solver defaults come
from the stages that use them (``MCBAConfig``, the keyframe selector, ``MappingConfig``),
so the tuned values are written once. A stage's own settings are a nested section of its
stage's: ``tracking.stereo`` (:class:`~mcgs_warp.frontend.stereo.StereoConfig`),
``tracking.keypoint_matching`` (:class:`~mcgs_warp.frontend.keypoint_tracker.KeypointConfig`),
``tracking.odometry`` (:class:`~mcgs_warp.frontend.keypoint_odometry.OdometryConfig`),
``tracking.flow`` (:class:`~mcgs_warp.frontend.flow.FlowConfig`) and ``tracking.graph`` (:class:`~mcgs_warp.ba.edges.GraphConfig`), each key documented there. ``configs/*.yaml`` hold only what a run changes."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from ..ba.edges import GraphConfig
from ..ba.mcba import MCBAConfig
from ..errors import InputError
from ..frontend.flow import FlowConfig
from ..frontend.keyframes import THRESHOLD_RAD
from ..frontend.keypoint_odometry import OdometryConfig
from ..frontend.keypoint_tracker import KeypointConfig
from ..frontend.stereo import StereoConfig
from ..mapping.mapper import MappingConfig


#: allowed values of string options: (section, key) -> choices
CHOICES = {
    ("tracking", "depth"): ("auto", "sensor", "stereo", "none"),
    ("tracking", "correspondences"): ("estimated", "ground-truth", "none"),
}


#: smallest allowed values where 0 (or 1) would fail or silently switch a stage off:
#: (section, key) -> (minimum, strict: the value must exceed it, what the key needs)
MINIMUMS = {
    ("tracking", "stride"): (1, False, "the reduced grid keeps every stride-th pixel"),
    ("tracking", "window"): (2, False, "MCBA needs the new keyframe and at least one other"),
    ("tracking", "temporal_radius"): (1, False, "each view needs an edge to another keyframe"),
    ("tracking", "mcba_iterations"): (1, False, "0 would never move a pose"),
    ("tracking", "flow_rounds"): (1, False, "each keyframe needs one MCBA round"),
    ("tracking", "huber_px"): (0.0, True, "0 would give every residual zero weight"),
    ("tracking", "lm_lambda"): (0.0, True, "the damping is multiplied, never added: 0 stays 0"),
    ("tracking", "jdsa_rows"): (1, False, "a scale grid has at least one node per axis"),
    ("tracking", "jdsa_cols"): (1, False, "a scale grid has at least one node per axis"),
    ("mapping", "insert_stride"): (1, False, "new Gaussians every insert_stride-th pixel"),
    ("mapping", "fill_opacity"): (0.0, True, "an opacity of 0 is a logit of minus infinity"),
    ("mapping", "background_cube"): (0, False, "texels per cube face"),
    ("tracking.stereo", "scale"): (1, False, "the sweep runs at 1/scale resolution"),
    ("tracking.stereo", "planes"): (2, False, "a sweep needs at least two depth hypotheses"),
    ("tracking.stereo", "plane_px"): (0.0, True, "the epipolar step between hypotheses"),
    ("tracking.stereo", "radius"): (1, False, "the ZNCC window is (2 radius + 1)^2 pixels"),
    ("tracking.stereo", "near"): (0.0, True, "the nearest hypothesis' inverse depth"),
    ("tracking.stereo", "temporal_near"): (0.0, True, "the nearest temporal hypothesis' inverse depth"),
    ("tracking.stereo", "max_cost"): (0.0, True, "0 would reject every match"),
    ("tracking.stereo", "max_ratio"): (0.0, True, "0 would reject every match"),
    ("tracking.keypoint_matching", "features"): (1, False, "keypoints per view"),
    ("tracking.keypoint_matching", "ratio"): (0.0, True, "0 would reject every match"),
    ("tracking.keypoint_matching", "inlier_rad"): (0.0, True, "0 would leave no inlier"),
    ("tracking.keypoint_matching", "min_inliers"): (4, False, "a PnP pose needs at least 4 points"),
    ("tracking.keypoint_matching", "keyframes"): (1, False, "a keyframe is matched against at least one other"),
    ("tracking.odometry", "frames"): (1, False, "a frame is matched against at least the one before"),
    ("tracking.odometry", "window"): (2, False, "the bundle adjustment needs the new frame and one other"),
    ("tracking.odometry", "iterations"): (1, False, "0 would never move a pose"),
    ("tracking.odometry", "stride"): (1, False, "the residuals' pixel unit"),
    ("tracking.odometry", "huber_px"): (0.0, True, "0 would give every residual zero weight"),
    ("tracking.flow", "patch_size"): (1, False, "DIS patches are at least 1 px"),
    ("tracking.flow", "sigma"): (0.0, True, "the confidence divides by it"),
    ("tracking.flow", "photo_sigma"): (0.0, True, "the photometric factor divides by it"),
    ("tracking.flow", "settled_px"): (0.0, False, "a distance in pixels"),
    ("tracking.graph", "sample"): (1, False, "overlap is measured on every sample-th grid pixel"),
    ("tracking.graph", "max_angle"): (0.0, True, "0 would link no pair"),
    ("refinement", "steps_per_keyframe"): (0, False, "steps per registered keyframe (0: no limit)"),
    ("tracking.graph", "loop_max_per_view"): (1, False, "a loop candidate needs a partner (refinement.global_ba_iterations: 0 skips loops)"),
}

#: largest allowed values: (section, key) -> (maximum, strict, what the key needs)
MAXIMUMS = {
    ("mapping", "fill_opacity"): (1.0, True, "an opacity of 1 is a logit of infinity"),
    ("mapping", "prune_screen"): (1.0, False, "a share of the image width"),
    ("tracking.stereo", "max_ratio"): (1.0, False, "best / second-best cost"),
    ("tracking.stereo", "max_disparity"): (1.0, False, "a share of the image width"),
    ("tracking.keypoint_matching", "ratio"): (1.0, False, "nearest / second nearest descriptor distance"),
    ("tracking.keypoint_matching", "min_inlier_ratio"): (1.0, False, "a share of the matches"),
    ("tracking.flow", "settled_outliers"): (1.0, False, "a share of the edge's pixels"),
    ("tracking.flow", "min_confident"): (1.0, False, "a share of the view's grid pixels"),
    ("tracking.graph", "max_angle"): (180.0, False, "degrees between optical axes"),
    ("tracking.graph", "loop_max_angle"): (180.0, False, "degrees between optical axes"),
    ("tracking.graph", "min_overlap"): (1.0, False, "a share of the view"),
    ("tracking.graph", "loop_min_overlap"): (1.0, False, "a share of the view"),
    ("refinement", "global_ba_min_overlap"): (1.0, False, "a share of the view"),
}

#: keys of a nested stage section that the run sets from another key: (section, key) -> which
DERIVED = {
    ("tracking.graph", "max_per_view"): "tracking.temporal_radius sets it (2 x temporal_radius)",
}


@dataclass
class TrackingConfig:
    depth: str = "auto"  # auto | sensor | stereo | none (see mcgs_warp.frontend.depth.choose_prior)
    correspondences: str = "estimated"  # estimated | ground-truth (oracle, synthetic sequences only) | none (no dense edges: keypoint tracks alone, the sparse core as an ablation)
    max_width: int = 640  # px: images are resampled (intrinsics scaled) so the widest camera is at most this wide for tracking and mapping (0: native resolution)
    stride: int = 8  # px: inverse depth and flow live on every 8th pixel (the reduced grid)
    window: int = 8  # keyframes in the MCBA sliding window
    keyframe_flow: float = THRESHOLD_RAD  # rad: new keyframe when the mean flow since the last, in view angle (px / focal length), reaches this (0: every frame; 0.055: 10 px at a 180 px focal length, 20 px for KITTI at 640 px wide)
    temporal_radius: int = 2  # each view links to up to 2x this many overlapping views of the window (nearest first); the last radius+1 keyframes' edges are re-matched between MCBA rounds
    cross_view: bool = True  # edges between overlapping cameras at one timestamp (eq. 8); never with exact sensor depth, which already fixes the depth they measure
    mcba_iterations: int = MCBAConfig.iterations  # Levenberg-Marquardt iterations per MCBA solve
    huber_px: float = MCBAConfig.huber_delta  # grid px: Huber threshold of the reprojection residuals
    lm_lambda: float = MCBAConfig.lm_lambda  # MCBA's initial Levenberg-Marquardt damping, relative to the diagonal (global BA starts from it too)
    prior_weight: float = 30.0  # px^2 m^2: weight of a metric depth prior (sensor, stereo, monocular) in inverse depth, times its confidence
    jdsa: bool = True  # fit the JDSA scale grids (eq. 5) after every MCBA round, for inexact priors
    jdsa_rows: int = 4  # JDSA scale grid per view: rows ...
    jdsa_cols: int = 6  # ... and columns of bilinearly interpolated scale nodes
    min_confident: float = 0.05  # a new keyframe with confident correspondences on fewer of its grid pixels than this fraction is a tracking failure
    max_residual_ratio: float = 10.0  # ... and so is one whose final robust cost per unit of correspondence weight exceeds this times the run's median
    keypoints: bool = True  # anchor each new keyframe's pose by keypoints matched against recent keyframes (multi-camera PnP; false: the constant-velocity prediction alone) and relocalize failed keyframes by them
    keypoint_weight: float = 0.0  # confidence of one keypoint track observation in MCBA (a dense correspondence's is its DIS confidence, 0-1); 0: keypoints anchor and relocalize only (KITTI excerpt: SE(3) ATE 0.764 m at 0, 0.816 m at 1; docs/results.md)
    odometry_weight: float = 1.0  # keypoint odometry (every frame, with keypoints): weight of its measured motion between consecutive keyframes in MCBA, times its information (its covariance carries its keypoints' measured variance; MCBA weighs it against the dense residuals' measured noise, mcgs_warp/ba/variance.py). 0: it only starts new keyframes and places the frames between them
    depth_weight: float = 30.0  # px^2 m^2: weight of the sensor-depth alignment residual (exact sensor depth only: a view's depth moved into another against that view's depth, so textureless surfaces with good depth still track; 0: off)
    flow_rounds: int = 2  # MCBA (+ JDSA) rounds per keyframe; between them correspondences follow the new geometry
    variance_components: bool = MCBAConfig.variance_components  # weight keypoint tracks and odometry against the dense residuals by the noise each measurably carries (robust scale, redundancy, the dense field's correlation; mcgs_warp/ba/variance.py); false: nominal weights
    stereo: StereoConfig = field(default_factory=StereoConfig)  # the rig's sweep stereo (depth prior without a depth sensor, cross-view matches): mcgs_warp/frontend/stereo.py
    keypoint_matching: KeypointConfig = field(default_factory=KeypointConfig)  # SIFT matching and multi-camera PnP of the keyframe anchor and the keypoint odometry: mcgs_warp/frontend/keypoint_tracker.py
    odometry: OdometryConfig = field(default_factory=OdometryConfig)  # the keypoint odometry's sliding window: mcgs_warp/frontend/keypoint_odometry.py
    flow: FlowConfig = field(default_factory=FlowConfig)  # the DIS correspondences of MCBA's edges: mcgs_warp/frontend/flow.py
    graph: GraphConfig = field(default_factory=GraphConfig)  # which views MCBA links (overlap, angles) and loop closure in global BA: mcgs_warp/ba/edges.py


@dataclass
class MappingRunConfig(MappingConfig):
    """The mapper's settings (defaults and units in ``MappingConfig``) plus its schedule."""

    iterations_per_keyframe: int = 8  # mapping iterations (Adam steps) after each new keyframe


@dataclass
class RefinementConfig:
    """The offline stage's settings: the global-BA backend's (``global_ba_*``,
    :mod:`~mcgs_warp.system.backend`), the photo-consistent depth targets' and joint refinement's."""

    global_ba_iterations: int = 4  # LM iterations of the offline MCBA over all keyframes (0: none)
    global_ba_radius: int = 6  # keyframes: its edges link overlapping views up to this far apart (longer baselines than online, so far depth is measured), plus confirmed loop edges
    global_ba_min_overlap: float = 0.1  # reprojected overlap (a share of the view, both ways) a long edge needs: less than the window's tracking.graph.min_overlap, since guided flow matches what there is
    photo_depth_radius: int = 3  # keyframes: after global BA each estimated depth target is checked against the same camera this many keyframes either side and the rig's overlapping cameras (PatchMatch-style propagation; 0: off; never for exact sensor depth; runs with global BA, so global_ba_iterations 0 skips it too)
    photo_depth_sources: int = 3  # ... matching each view against only this many of those views, the best by MVSNet's view score (parallax near 5 degrees over shared points; 0: all): KITTI excerpt 0.91x the run, the pass 0.53x, held-out PSNR 22.36 -> 22.63 dB (all 4-7 views before)
    photo_depth_min_views: int = 2  # after that pass a target pixel is kept only where at least this many of the same views' targets put the point within 5 % of it (geometric consistency, as multi-view stereo fusion; 0: keep all)
    iterations: int = 360  # joint refinement iterations (Adam steps) of map, poses and exposures (120 until 2026-11-27: seed 0 RGB only depth L1 0.106 -> 0.099 m, 28.94 -> 29.43 dB; held-out seed 1 0.100 -> 0.095 m; the demo 30.5 -> 30.8 dB)
    steps_per_keyframe: int = 60  # ... but at most this many per registered keyframe (each step renders one keyframe's cameras): 360 steps over DDAD's 2 keyframes x 6 cameras overfit them (held-out PSNR 15.74 dB at 360, 16.30 at 120; depth against LiDAR better in all 6 cameras at 120); runs of 6 keyframes or more keep 360 (0: no limit)
    poses: bool = True  # refine the rig poses through the renderer
    exposure: bool = True  # fit a per-image affine colour (gain, bias)


@dataclass
class OutputConfig:
    renders: int = 4  # keyframes rendered beside their input images


@dataclass
class RunConfig:
    seed: int = 0  # random seed of the mapper (runs are deterministic for a seed)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingRunConfig = field(default_factory=MappingRunConfig)
    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def to_dict(self) -> dict:
        """Every settable key (what a run writes as its resolved config.yaml, which loads back)."""
        d = dataclasses.asdict(self)
        for section, key in DERIVED:
            node = d
            for part in section.split("."):
                node = node[part]
            del node[key]
        return d


def _at_least(value, src, section, key, name):
    low, strict, why = MINIMUMS.get((section, key), (0, False, ""))
    if value < low or (strict and value <= low):
        raise InputError(src, name, f"expected {'more than' if strict else 'at least'} {low} ({why}), got {value!r}")
    if (section, key) in MAXIMUMS:
        high, strict, why = MAXIMUMS[(section, key)]
        if value > high or (strict and value >= high):
            raise InputError(src, name, f"expected {'less than' if strict else 'at most'} {high} ({why}), got {value!r}")
    return value


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
        if (prefix, key) in DERIVED:
            raise InputError(src, name, f"not settable: {DERIVED[(prefix, key)]}")
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
            kwargs[key] = _at_least(value, src, prefix, key, name)
        elif isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value or value < 0:
                raise InputError(src, name, f"expected a non-negative number, got {value!r}")
            kwargs[key] = _at_least(float(value), src, prefix, key, name)
        elif isinstance(default, str):
            choices = CHOICES.get((prefix, key))
            if not isinstance(value, str) or (choices and value not in choices):
                expected = " | ".join(choices) if choices else "a string"
                raise InputError(src, name, f"expected {expected}, got {value!r}")
            kwargs[key] = value
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
