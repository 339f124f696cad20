"""What a run leaves in its folder (every file written atomically):

* ``trajectory.txt`` (rig body ``T_w_b``, TUM) and ``trajectory_<camera>.txt`` (``T_w_c``)
* ``map.usdc`` (``UsdVol.ParticleField3DGaussianSplat`` + keyframe cameras), ``map.ply`` (3DGS)
* ``renders/keyframe_<k>_<camera>.png``: input | render | depth (dimmed where guessed), for a few keyframes, and
  ``renders/frame_<i>_<camera>.png``: input | render of one frame the map was not fitted to
* ``depth/keyframe_<k>_<camera>.png``: every keyframe view's rendered median depth, 16-bit
  millimetres, 0 = none or covered less than half (what RGB-D datasets use); ``confidence/keyframe_<k>_<camera>.png``
  beside it: 8-bit, 255 where that depth was measured (most of the rendered weight from Gaussians
  placed at a measured depth) and stands for one surface, 128 where it was measured but the blend
  mixes surfaces (a depth edge: the median may be either), 0 where it was guessed by the fill or
  there is none (:func:`confidence_levels`); ``images/keyframe_<k>_<camera>.jpg``: its
  input image (what ``mcgs-slam view`` shows in the keyframe's frustum)
* ``metrics.json``: ATE (SE(3)- and Sim(3)-aligned; over every frame and over keyframes
  only), evo-style RPE and path length when ground truth exists, PSNR, SSIM over the
  keyframe views and over held-out non-keyframe frames, depth L1 (median depth; the
  alpha-normalized depth's beside it; on measured, mixed and guessed pixels) and its coverage against
  the sequence's exact depth (``gt/`` or exact sensor depth; never used by the run itself), the depth source and
  correspondences used, for an inexact prior its error before and after JDSA's scale grids,
  counts and timings
* ``plots/trajectory.png`` (top view in the plane orthogonal to gravity where the reader knows
  it, else the motion's principal plane; estimate vs ground truth, SE(3)-aligned for a run
  with metric scale, else Sim(3)), ``plots/mapping.png``
  (loss and PSNR per mapping iteration)
* ``groundtruth_in_map.txt``: where ground truth exists, it moved into the map's frame (the
  inverse of the SE(3) alignment for a run with metric scale, else of the Sim(3) one), TUM
* ``config.yaml``: the resolved run configuration; ``rig.yaml`` and ``keyframes.txt``
  (keyframe rig poses, TUM) so that ``mcgs-slam export`` can rebuild the USD cameras
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..data.sequence import depth_to_mm
from ..data.trajectory import Trajectory, write_tum
from ..errors import InputError
from ..eval.metrics import psnr, ssim
from ..eval.plots import plot_mapping, plot_trajectory
from ..eval.trajectory import associate, evaluate, umeyama
from ..io import atomic_write, write_image
from ..io.ply import write_ply
from ..io.usd import write_usd
from ..kernels import Views
from ..rig import save_rig


def depth_colormap(depth: np.ndarray, vmax: float) -> np.ndarray:
    import cv2

    d = np.clip(depth / max(vmax, 1e-6), 0, 1)
    rgb = cv2.applyColorMap((255 * (1 - d)).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1] / 255.0
    return np.where(depth[..., None] > 0, rgb, 0.0)


def groundtruth_in_map(est: Trajectory, gt: Trajectory, with_scale: bool) -> Trajectory:
    """Ground-truth poses moved into the estimate's (the map's) frame: the inverse of the
    alignment that maps the estimate onto the ground truth (Umeyama over matched positions)."""
    i, j = associate(est.timestamps, gt.timestamps)
    s, R, t = umeyama(est.positions[i], gt.positions[j], with_scale)  # gt ~ s R est + t
    T = np.array(gt.poses, dtype=np.float64, copy=True)
    T[:, :3, :3] = R.T @ T[:, :3, :3]
    T[:, :3, 3] = (T[:, :3, 3] - t) @ R / s
    return Trajectory(gt.timestamps, T)


def keyframe_views(slam):
    """Render every keyframe's views at their final poses, exposure applied: yields (k, c,
    rendered colour, median depth (where the transmittance crosses 0.5; 0 where the map covers
    less than half), alpha-normalized depth, rendered alpha, confidence level
    (:func:`confidence_levels`), input image, frame index)."""
    m, buf = slam.mapper, slam.buf
    poses = buf.get_poses()
    exposure = m.buf.exposure.numpy()  # [capacity, C, 2] (log a, b)
    for k in range(len(buf)):
        views = Views.create(m.cams, buf.rig.camera_poses(poses[k]), buf.device)
        colour, out = m.render(views)
        col, med, dep, alpha = colour.numpy(), out.median_depth.numpy(), out.depth.numpy(), out.alpha.numpy()
        level = confidence_levels(*m.depth_confidence(out, views), med)
        for c, spec in enumerate(buf.rig.cameras):
            a, b = np.exp(exposure[k, c, 0]), exposure[k, c, 1]
            crop = (c, slice(0, spec.height), slice(0, spec.width))
            yield k, c, np.clip(a * col[crop] + b, 0, 1), med[crop], dep[crop], alpha[crop], level[crop], buf.image(k, c), buf.frame_index[k]


MEASURED, MIXED, GUESSED = 255, 128, 0  # the confidence PNGs' levels
MAX_DEPTH_SPREAD = 0.1  # relative spread of the blended depths around the median beyond which a pixel mixes surfaces (chosen on street seed 11, RGB only: 73 % of the pixels measured and within it at 0.26 m L1, 23 % beyond it at 1.28 m; held-out seed 12: 73 % at 0.39 m, 3.3 m beyond)


def confidence_levels(share: np.ndarray, spread: np.ndarray, median_depth: np.ndarray) -> np.ndarray:
    """Per pixel (any shape, from :meth:`Mapper.depth_confidence`): ``MEASURED`` where the
    median depth is mostly measured (share >= 0.5) and one surface (spread at most
    ``MAX_DEPTH_SPREAD``), ``MIXED`` where measured but mixing surfaces, ``GUESSED`` where
    guessed or without a median depth (uint8)."""
    measured = (median_depth > 0) & (share >= 0.5)
    return np.where(measured, np.where(spread <= MAX_DEPTH_SPREAD, MEASURED, MIXED), GUESSED).astype(np.uint8)


def _mean_of(acc) -> float | None:
    return acc[0] / acc[1] if acc[1] else None


GUESSED_SHADE = 0.4  # brightness of guessed (filled) depth in the render panels' depth image

MAX_HELD_OUT_FRAMES = 20  # non-keyframe frames rendered for psnr_nonkeyframe_db (evenly spaced)


def held_out_frames(n_frames: int, keyframe_frames, max_frames: int = MAX_HELD_OUT_FRAMES) -> list:
    """Up to ``max_frames`` evenly spaced frame indices that are not keyframes."""
    others = np.setdiff1d(np.arange(n_frames), np.asarray(keyframe_frames, int))
    if not len(others):
        return []
    return others[np.unique(np.linspace(0, len(others) - 1, min(max_frames, len(others))).round().astype(int))].tolist()


def held_out_views(slam, trajectory: Trajectory, frames):
    """Render ``frames`` (non-keyframes: images the map was never fitted to) at their
    estimated (interpolated) rig poses, with the exposure of the keyframe nearest in time:
    yields (frame index, c, rendered colour, input image)."""
    m, buf = slam.mapper, slam.buf
    kf = np.array(buf.frame_index)
    exposure = m.buf.exposure.numpy()
    for f in frames:
        k = int(np.argmin(np.abs(kf - f)))
        colour, _ = m.render(Views.create(m.cams, buf.rig.camera_poses(trajectory.poses[f]), buf.device))
        col = colour.numpy()
        images = slam.seq[f].images
        for c, spec in enumerate(buf.rig.cameras):
            a, b = np.exp(exposure[k, c, 0]), exposure[k, c, 1]
            yield f, c, np.clip(a * col[c, : spec.height, : spec.width] + b, 0, 1), images[c]


def prior_errors(slam) -> tuple[float | None, float | None]:
    """Mean |depth - exact depth| (m) of an inexact metric prior (stereo, monocular-style) on
    MCBA's grid, as given and times JDSA's scale grids (eq. 5), over every keyframe view:
    what JDSA did to the prior. ``(None, None)`` without such a prior or without exact depth."""
    from ..ba.jdsa import scale_field
    from ..frontend.depth import grid_depth

    buf, seq = slam.buf, slam.seq
    if not slam.tracker.prior.metric or slam.tracker.exact_depth:
        return None, None
    raw, scaled = [], []
    for k in range(len(buf)):
        gt = seq.gt_depths(buf.frame_index[k])
        if gt is None:
            return None, None
        exact = grid_depth(gt, seq.rig, buf.stride, (buf.h, buf.w))
        prior, grids = buf.depth_prior[k].numpy(), buf.scales[k].numpy()
        for c in range(len(seq.rig)):
            ok = (exact[c] > 0) & (prior[c] > 0)
            if ok.any():
                raw.append(np.abs(prior[c] - exact[c])[ok])
                scaled.append(np.abs(prior[c] * scale_field(grids[c], buf.h, buf.w) - exact[c])[ok])
    if not raw:
        return None, None
    return float(np.concatenate(raw).mean()), float(np.concatenate(scaled).mean())


MAX_METRIC_SCALE_ERROR = 0.1  # a metric run whose Sim(3) scale is further from 1 is worth a word


def scale_warning(metric_scale: bool, sim3_scale: float) -> str | None:
    """What to tell a user whose run claims metric scale but whose trajectory needs a
    Sim(3) scale far from 1 to fit the ground truth (depth in another unit, a wrong
    baseline), or None. Images alone cannot tell a depth unit from a scene size."""
    if not metric_scale or abs(sim3_scale - 1.0) <= MAX_METRIC_SCALE_ERROR:
        return None
    return (f"the run claims metric scale, but its trajectory needs a Sim(3) scale of {sim3_scale:.3f} to fit the ground truth: "
            f"check the depth unit (our depth PNGs: millimetres; TUM's: 1/5000 m) and the rig's baselines (T_b_c, m)")


class RelativeErrors:
    """Relative depth errors |d - d_true| / d_true of many pixels as a histogram (0.05 % bins up
    to 200 %, one bin beyond): their median without holding every pixel of every view (2.0 where
    it lies beyond: at least 200 %)."""

    BIN, N = 5e-4, 4000

    def __init__(self):
        self.counts = np.zeros(self.N + 1, np.int64)

    def add(self, rel: np.ndarray) -> None:
        self.counts += np.bincount(np.minimum((rel / self.BIN).astype(np.int64), self.N), minlength=self.N + 1)

    def median(self) -> float | None:
        n = int(self.counts.sum())
        if not n:
            return None
        i = int(np.searchsorted(np.cumsum(self.counts), (n + 1) / 2))
        return round((i + 0.5) * self.BIN, 4) if i < self.N else round(self.N * self.BIN, 4)


def _quantiles(values) -> dict | None:
    return {"min": round(float(np.min(values)), 4), "median": round(float(np.median(values)), 4)} if len(values) else None


def write_outputs(out_dir, slam, result, seconds_total: float) -> dict:
    out = Path(out_dir)
    seq, buf, rig = slam.seq, slam.buf, slam.seq.rig
    traj = result.trajectory
    write_tum(out / "trajectory.txt", traj)
    T_w_c = rig.camera_poses(traj.poses)
    for c, spec in enumerate(rig.cameras):
        write_tum(out / f"trajectory_{spec.name}.txt", Trajectory(traj.timestamps, T_w_c[:, c]))

    params = slam.mapper.map.to_numpy()
    kf_poses = buf.get_poses()
    cams = [(f"kf{k:03d}_{spec.name}", kf_poses[k] @ spec.T_b_c, spec) for k in range(len(buf)) for spec in rig.cameras]
    write_usd(out / "map.usdc", params, cams)
    write_ply(out / "map.ply", params)
    save_rig(rig, out / "rig.yaml")
    write_tum(out / "keyframes.txt", Trajectory(np.array(buf.timestamps), kf_poses))
    odometry = slam.tracker.odometry.trajectory(seq.timestamps) if slam.tracker.odometry is not None else None  # none from given poses or with keypoints off
    if odometry is not None:
        write_tum(out / "trajectory_odometry.txt", odometry)

    # Image metrics over every keyframe view; a few renders beside their inputs.
    n_render = slam.cfg.output.renders
    show = set(np.linspace(0, len(buf) - 1, min(n_render, len(buf))).astype(int).tolist()) if n_render else set()
    psnrs, ssims, depth_err, mixed_err, covered, with_depth = [], [], [], [], 0, 0
    by_level = {MEASURED: [0.0, 0], MIXED: [0.0, 0], GUESSED: [0.0, 0]}  # per confidence level: sum of |depth error| (m), pixels
    frames: dict = {}
    covers = [[] for _ in rig.cameras]  # per camera: share of each keyframe view the map covers
    measured_px = [[0, 0] for _ in rig.cameras]  # per camera: pixels with a median depth, of which measured
    rel_all, rel_measured = [RelativeErrors() for _ in rig.cameras], [RelativeErrors() for _ in rig.cameras]  # per camera: relative depth errors on the exact-depth pixels the render covers, and on those marked measured
    true_px = [[0, 0] for _ in rig.cameras]  # per camera: exact-depth pixels, of which the render covers
    for k, c, col, dep, mixed, alpha, level, img, fidx in keyframe_views(slam):
        covers[c].append(float(np.mean(alpha > 0.5)))
        measured = level == MEASURED
        measured_px[c][0] += int((dep > 0).sum())
        measured_px[c][1] += int(measured.sum())
        psnrs.append(psnr(col, img))
        ssims.append(ssim(col, img, with_grad=False)[0])
        if fidx not in frames:
            frames = {fidx: seq.gt_depths(fidx)}  # exact depth (evaluation only), loaded once per keyframe
        sensor = frames[fidx][c] if frames[fidx] is not None else None
        write_image(out / "depth" / f"keyframe_{k:03d}_{rig.cameras[c].name}.png", depth_to_mm(dep))
        write_image(out / "confidence" / f"keyframe_{k:03d}_{rig.cameras[c].name}.png", level / 255.0)
        write_image(out / "images" / f"keyframe_{k:03d}_{rig.cameras[c].name}.jpg", img)
        if sensor is not None:
            ok = (sensor > 0) & (dep > 0)
            covered, with_depth = covered + int(ok.sum()), with_depth + int((sensor > 0).sum())
            true_px[c][0] += int((sensor > 0).sum())
            true_px[c][1] += int(ok.sum())
            rel = np.abs(dep[ok] - sensor[ok]) / sensor[ok]
            rel_all[c].add(rel)
            rel_measured[c].add(rel[measured[ok]])
            if ok.any():
                err = np.abs(dep[ok] - sensor[ok])
                depth_err.append(float(err.mean()))
                for lv, acc in by_level.items():
                    sel = level[ok] == lv
                    acc[0] += float(err[sel].sum())
                    acc[1] += int(sel.sum())
            ok_mixed = (sensor > 0) & (mixed > 0)
            if ok_mixed.any():
                mixed_err.append(float(np.abs(mixed[ok_mixed] - sensor[ok_mixed]).mean()))
        if k in show:
            vmax = float(np.percentile(sensor[sensor > 0], 95)) if sensor is not None and (sensor > 0).any() else float(np.percentile(dep[dep > 0], 95)) if (dep > 0).any() else 1.0
            shade = np.where(level == GUESSED, GUESSED_SHADE, 1.0)[..., None]  # guessed depth dimmed: what the confidence PNG says
            write_image(out / "renders" / f"keyframe_{k:03d}_{rig.cameras[c].name}.png", np.concatenate([img, col, shade * depth_colormap(dep, vmax)], axis=1))

    held_psnr, held_ssim = [], []
    held = held_out_frames(len(traj), buf.frame_index)
    for f, c, col, img in held_out_views(slam, traj, held):
        held_psnr.append(psnr(col, img))
        held_ssim.append(ssim(col, img, with_grad=False)[0])
        if n_render and f == held[len(held) // 2]:
            write_image(out / "renders" / f"frame_{f:06d}_{rig.cameras[c].name}.png", np.concatenate([img, col], axis=1))

    prior_l1, prior_jdsa_l1 = prior_errors(slam)
    metrics = {
        "ate_rmse_m": None,
        "path_length_m": float(np.linalg.norm(np.diff(traj.positions, axis=0), axis=1).sum()),
        "psnr_db": float(np.mean(psnrs)),
        "ssim": float(np.mean(ssims)),
        "psnr_nonkeyframe_db": float(np.mean(held_psnr)) if held_psnr else None,  # frames the map was not fitted to
        "ssim_nonkeyframe": float(np.mean(held_ssim)) if held_ssim else None,
        "n_nonkeyframe_views": len(held_psnr),
        "depth_l1_m": float(np.mean(depth_err)) if depth_err else None,  # the rendered median depth (the depth PNGs') against exact depth
        "depth_coverage": covered / with_depth if with_depth else None,  # fraction of exact-depth pixels the render gives a median depth (alpha above 0.5; depth_l1_m scores only those)
        "depth_l1_alpha_normalized_m": float(np.mean(mixed_err)) if mixed_err else None,  # the alpha-normalized depth (mixes faint Gaussians with those behind) over every pixel it covers
        "depth_l1_measured_m": _mean_of(by_level[MEASURED]),  # the median depth's error on the pixels the confidence PNGs mark measured (one surface) ...
        "depth_l1_mixed_m": _mean_of(by_level[MIXED]),  # ... measured but mixing surfaces (depth edges) ...
        "depth_l1_filled_m": _mean_of(by_level[GUESSED]),  # ... and guessed (filled); pixel-weighted, unlike depth_l1_m's mean over views
        "depth_measured_fraction": by_level[MEASURED][1] / scored if (scored := sum(v[1] for v in by_level.values())) else None,  # share of the scored pixels marked measured
        "measured_fraction_per_camera": {spec.name: measured_px[c][1] / measured_px[c][0] if measured_px[c][0] else None for c, spec in enumerate(rig.cameras)},  # per camera: share of the pixels with a rendered depth that the confidence marks measured (needs no ground truth)
        # per camera against exact depth (a LiDAR's points, a renderer's depth) where the sequence has it: the median relative error of the rendered median depth, the share of exact-depth pixels it covers, and the median on the pixels the confidence marks measured
        "depth_vs_exact_per_camera": {spec.name: {"median_rel": rel_all[c].median(), "coverage": true_px[c][1] / true_px[c][0], "median_rel_measured": rel_measured[c].median()} for c, spec in enumerate(rig.cameras) if true_px[c][0]} or None,
        "map_coverage_per_camera": {spec.name: _quantiles(covers[c]) for c, spec in enumerate(rig.cameras)},  # share of a keyframe view's pixels the map covers (rendered alpha > 0.5): min and median over keyframes
        "depth_source": slam.tracker.prior.name,
        "prior_l1_m": prior_l1,  # the inexact prior against exact depth, before JDSA ...
        "prior_jdsa_l1_m": prior_jdsa_l1,  # ... and after its scale grids (equal with --no-jdsa)
        "jdsa": slam.tracker.jdsa_active,
        "correspondences": slam.cfg.tracking.correspondences,
        "n_gaussians": len(slam.mapper.map),
        "n_keyframes": len(buf),
        "loop_edges": slam.backend.confirmed_loops,  # revisit candidates global BA confirmed
        "n_frames": len(seq),
        "seconds_total": float(seconds_total),
        "tracking_failures": len(slam.tracker.failures),  # keyframe solves judged failed (each one warning line, then recovered or kept at the prediction)
        "tracking_failure_frames": slam.tracker.failures,
        "tracking_lost_frames": [int(buf.frame_index[k]) for k in slam.tracker.lost],  # keyframes nothing tracked or relocalized (kept at the prediction, not mapped)
        "confident_fraction": _quantiles([h["confident"] for h in slam.tracker.health]),  # per keyframe solve: fraction of its grid pixels with a confident correspondence (min, median)
        "confident_fraction_per_camera": {c.name: _quantiles([h["confident_per_camera"][i] for h in slam.tracker.health]) for i, c in enumerate(seq.rig.cameras)} if slam.tracker.health else None,
        "keypoint_inliers": _quantiles([h["keypoint_inliers"] or 0 for h in slam.tracker.health]) if slam.tracker.keypoints is not None else None,  # per keyframe solve: PnP inliers of its keypoint pose (0: none; min, median)
        "keypoint_anchored": sum(h["keypoint_inliers"] is not None for h in slam.tracker.health) if slam.tracker.keypoints is not None else None,  # keyframe solves started from a keypoint pose (else constant velocity)
        "dense_sigma_px": _quantiles([h["dense_sigma"] * buf.stride for h in slam.tracker.health if h.get("dense_sigma") is not None]),  # per keyframe solve: the dense residuals' measured noise (full-resolution px; min, median)
        "dense_correlation_factor": _quantiles([h["dense_kappa"] for h in slam.tracker.health if h.get("dense_kappa") is not None]),  # ... and how many grid pixels count as one independent measurement (kappa, mcgs_warp/ba/variance.py)
        "metric_scale": slam.tracker.metric_scale,
        "seconds": {k: round(v, 3) for k, v in result.seconds.items()},
    }
    gt_xyz, times = None, traj.timestamps
    aligned, label = traj.positions, "ATE"
    sim3 = None
    if seq.groundtruth is not None:
        try:
            sim3 = evaluate(traj, seq.groundtruth, return_timestamps=True)
        except InputError as e:  # too few poses to align (a 2-keyframe scene): the rest of the run still counts
            from ..errors import warn

            warn(None, f"trajectory not evaluated: {e}; metrics.json holds the rest")
    if sim3 is not None:
        tm, aligned, gt_xyz, times = sim3
        se3, se3_aligned, _ = evaluate(traj, seq.groundtruth, with_scale=False)
        # RPE as a user compares it: metric runs as they are, others after the Sim(3) scale
        rpe = se3 if slam.tracker.metric_scale else tm
        metrics.update({"rpe_trans_m": rpe.rpe_trans_m, "rpe_rot_deg": rpe.rpe_rot_deg, "rpe_delta_frames": rpe.rpe_delta, "rpe_scale_corrected": not slam.tracker.metric_scale})
        if len(buf) >= 3:  # keyframes only: the poses the run estimated, none interpolated
            kf_traj = Trajectory(np.array(buf.timestamps), kf_poses)
            metrics.update({"ate_keyframes_rmse_m": evaluate(kf_traj, seq.groundtruth)[0].ate_rmse_m, "ate_keyframes_se3_rmse_m": evaluate(kf_traj, seq.groundtruth, with_scale=False)[0].ate_rmse_m})
        if odometry is not None and len(odometry) >= 3:  # the keypoint odometry alone, every frame it placed: the sparse core the dense system must not fall behind
            try:
                ot, _, _ = evaluate(odometry, seq.groundtruth, with_scale=False)
                metrics.update({"ate_odometry_se3_rmse_m": ot.ate_rmse_m, "ate_odometry_se3_percent_of_path": 100.0 * ot.ate_rmse_m / max(tm.path_length_m, 1e-12)})
            except InputError:
                pass  # too few of its frames match the ground truth
        metrics.update({"ate_rmse_m": tm.ate_rmse_m, "path_length_m": tm.path_length_m, "sim3_scale": tm.scale, "ate_percent_of_path": 100.0 * tm.ate_rmse_m / max(tm.path_length_m, 1e-12), "ate_se3_rmse_m": se3.ate_rmse_m, "ate_se3_percent_of_path": 100.0 * se3.ate_rmse_m / max(tm.path_length_m, 1e-12)})
        # a run that claims metric scale is judged without rescaling: the plot shows what a user gets
        aligned, label = (se3_aligned, "SE(3) ATE") if slam.tracker.metric_scale else (aligned, "Sim(3) ATE")
        write_tum(out / "groundtruth_in_map.txt", groundtruth_in_map(traj, seq.groundtruth, with_scale=not slam.tracker.metric_scale))
        why = scale_warning(slam.tracker.metric_scale, tm.scale)
        if why:
            from ..errors import warn

            warn(None, why)
    with atomic_write(out / "metrics.json") as f:
        json.dump(metrics, f, indent=2)
    plot_trajectory(out / "plots" / "trajectory.png", aligned, gt_xyz, times, gravity=seq.gravity, ate_label=label)
    if result.mapping_curve:
        plot_mapping(out / "plots" / "mapping.png", *(np.array(v, float) for v in zip(*result.mapping_curve)))
    import yaml

    with atomic_write(out / "config.yaml") as f:
        yaml.safe_dump(slam.cfg.to_dict(), f, sort_keys=False)
    return metrics
