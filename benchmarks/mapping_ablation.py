"""Mapping alone on a real sequence: each mapping rule switched off in turn, and the iteration budget.

The mapping's ceiling is measured without tracking: the sequence is run once with its ground-truth
poses held (``mcgs-slam map --poses groundtruth``, refinement off) and its keyframes, their final
depth targets (after global BA's photo-consistency pass) and up to 20 held-out frames are cached in
``OUT/keyframes.pkl``. Every row then maps those keyframes from scratch as a run does (each new
keyframe inserted, then ``iterations_per_keyframe`` steps over the last 8, then the joint refinement
with exposures, poses held) with one change to ``mapping:`` and reports PSNR and SSIM on the keyframes
and on the held-out frames, PSNR on the top third of the images (sky, tree tops) and the rest, the
map's size and the seconds. Default data: the KITTI excerpt (skips with a message where it is absent).

    python benchmarks/mapping_ablation.py [--data ../shared/data/kitti_stereo_excerpt] [--out out/mapping_ablation]
        [--rows default no-fill ...] [--budgets 1 2 4]

``--budgets`` repeats the default row with the online and refinement iterations times each factor.
Results land in ``OUT/mapping_ablation.json``.
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from pathlib import Path

import numpy as np

#: row name -> changes to MappingConfig (each undoes one rule of the default, or adds one)
ROWS = {
    "default": {},
    "no fill (nothing seeded where no depth)": {"insert_fill": False},
    "fill opaque (0.9)": {"fill_opacity": 0.9},
    "fill fainter (0.03)": {"fill_opacity": 0.03},
    "far field to 50 m only": {"insert_max_depth": 50.0},
    "no cube map (harmonics only)": {"background_cube": 0},
    "cube map 64": {"background_cube": 64},
    "sky segmentation on": {"sky": True},
    "no floater pruning": {"prune_floaters": False},
    "screen-size pruning 3 %": {"prune_screen": 0.03},
    "opacity reset every 200": {"opacity_reset_every": 200},
    "no densification": {"densify_every": 0},
}


def cache_keyframes(data: Path, path: Path) -> dict:
    """Run ``map --poses groundtruth`` without refinement and keep what mapping needs."""
    from mcgs_warp.data import open_sequence
    from mcgs_warp.data.resample import at_processing_resolution
    from mcgs_warp.system.config import load_run_config
    from mcgs_warp.system.outputs import held_out_frames
    from mcgs_warp.system.posed_mapping import PosedMapping
    from mcgs_warp.system.slam import Progress

    cfg = load_run_config(None)
    cfg.refinement.iterations = 0
    seq = at_processing_resolution(open_sequence(data), cfg.tracking.max_width)
    slam = PosedMapping(seq, cfg, seq.groundtruth, progress=Progress(True))
    slam.run()
    buf = slam.buf
    traj = slam.tracker.filler.trajectory()
    d = {
        "rig": seq.rig, "images": [list(x) for x in buf.images], "targets": {k: list(v) for k, v in buf.targets.items()},
        "poses": buf.get_poses(), "frame_index": list(buf.frame_index), "timestamps": list(buf.timestamps),
        "held": [(f, traj.poses[f], seq[f].images) for f in held_out_frames(len(traj), buf.frame_index)],
    }  # fmt: skip
    from mcgs_warp.io.atomic import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as f:
        pickle.dump(d, f)
    return d


def map_keyframes(d: dict, changes: dict, budget: float = 1.0, seed: int = 0) -> dict:
    """Map the cached keyframes with ``changes`` to the default MappingConfig; scores."""
    from mcgs_warp.buffer import KeyframeBuffer
    from mcgs_warp.eval.metrics import psnr, ssim
    from mcgs_warp.kernels import Views
    from mcgs_warp.mapping.mapper import Mapper
    from mcgs_warp.mapping.refine import joint_refinement
    from mcgs_warp.system.config import MappingRunConfig, RefinementConfig

    cfg = MappingRunConfig(**changes)
    per_kf, refine = round(cfg.iterations_per_keyframe * budget), round(RefinementConfig().iterations * budget)
    rig, K = d["rig"], len(d["images"])
    buf = KeyframeBuffer(rig, stride=8, capacity=K + 1, device="cpu")
    m = Mapper(buf, config=cfg, seed=seed)
    t0 = time.perf_counter()
    for k in range(K):
        buf.add(d["frame_index"][k], d["timestamps"][k], d["images"][k], d["poses"][k], np.zeros((len(rig), buf.h, buf.w), np.float32))
        m.add_keyframe(k, d["targets"][k])
        m.optimize(per_kf, keyframes=list(range(max(0, k - 7), k + 1)))
    joint_refinement(m, refine, poses=False, exposure=True)
    seconds = time.perf_counter() - t0
    ex = m.buf.exposure.numpy()

    def scores(col, img):
        h = img.shape[0] // 3
        return psnr(col, img), psnr(col[:h], img[:h]), psnr(col[h:], img[h:]), ssim(col, img, with_grad=False)[0]

    def exposed(col, k, c, spec):
        return np.clip(np.exp(ex[k, c, 0]) * col[c, : spec.height, : spec.width] + ex[k, c, 1], 0, 1)

    kf, held = [], []
    for k in range(K):
        col = m.render(m.views(k))[0].numpy()
        kf += [scores(exposed(col, k, c, s), d["images"][k][c]) for c, s in enumerate(rig.cameras)]
    frames = np.array(d["frame_index"])
    for f, T, images in d["held"]:
        k = int(np.argmin(np.abs(frames - f)))
        col = m.render(Views.create(m.cams, rig.camera_poses(T), buf.device))[0].numpy()
        held += [scores(exposed(col, k, c, s), images[c]) for c, s in enumerate(rig.cameras)]
    kf, held = np.mean(kf, 0), np.mean(held, 0)
    return {"psnr": kf[0], "psnr_top": kf[1], "psnr_rest": kf[2], "ssim": kf[3], "held_psnr": held[0], "held_top": held[1], "held_rest": held[2],
            "held_ssim": held[3], "gaussians": len(m.map), "iterations": per_kf * K + refine, "seconds": seconds}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti_stereo_excerpt"))
    parser.add_argument("--out", default="out/mapping_ablation")
    parser.add_argument("--rows", nargs="+", default=list(ROWS), help="rows to run (names of ROWS, quoted)")
    parser.add_argument("--budgets", type=float, nargs="*", default=[], help="the default row with this many times the iterations")
    args = parser.parse_args()
    data, out = Path(args.data), Path(args.out)
    if not data.is_dir():
        print(f"{data}: not found; this benchmark needs a sequence with ground-truth poses (the KITTI excerpt: ../shared/data/)")
        return
    cache = out / "keyframes.pkl"
    d = pickle.loads(cache.read_bytes()) if cache.is_file() else cache_keyframes(data, cache)
    runs = [(name, ROWS[name], 1.0) for name in args.rows] + [(f"default, {b:g}x iterations", {}, b) for b in args.budgets]
    results = {}
    print(f"{len(d['images'])} keyframes, {len(d['held'])} held-out frames; PSNR dB (top third / rest), SSIM")
    print(f"{'row':<42} {'keyframes':>20} {'held-out':>20} {'SSIM ho':>8} {'Gaussians':>9} {'iters':>6} {'s':>6}")
    for name, changes, budget in runs:
        r = map_keyframes(d, changes, budget)
        results[name] = {"changes": changes, "budget": budget, **{k: float(v) for k, v in r.items()}}
        print(f"{name:<42} {r['psnr']:>6.2f} ({r['psnr_top']:5.2f}/{r['psnr_rest']:5.2f}) {r['held_psnr']:>6.2f} ({r['held_top']:5.2f}/{r['held_rest']:5.2f}) "
              f"{r['held_ssim']:>8.3f} {r['gaussians']:>9d} {r['iterations']:>6d} {r['seconds']:>6.0f}", flush=True)
    from mcgs_warp.io.atomic import atomic_write

    with atomic_write(out / "mapping_ablation.json") as f:
        json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
