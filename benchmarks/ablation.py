"""Ablation on held-out synthetic worlds: depth regimes x scenes x seeds, mean and worst.

    python benchmarks/ablation.py [--scenes street indoor] [--seeds 11 12 13] [--frames 40]
        [--modes rgb mono mono-nojdsa exact rgb-sparse exact-sparse] [--rigs default] [--realism camera]
        [--room] [--oracle] [--out out/ablation]

For every scene (``synth --scene street | indoor | room``; no parameter was tuned on these seeds),
seed and mode it writes the sequence (``--realism camera`` images by default; the mono prior
with realistic errors) and runs the system with the defaults:

* ``rgb``: no depth (the rig's sweep stereo and cross-view edges carry the scale);
* ``mono``, ``mono-nojdsa``: the monocular-like prior with and without JDSA;
* ``exact``: exact sensor depth;
* ``rgb-sparse``, ``exact-sparse``: the system's own sparse core on the same data
  (``--correspondences none``: keypoint tracks in MCBA, no dense correspondences).

``--rigs front_back one`` repeats the mono modes on rigs where only the prior carries the
scale (``configs/rig_front_back.yaml``; the first camera alone), the regime JDSA is for.
``--room`` adds the built-in room at seed 0 with clean images and the smooth prior (the
figures before this benchmark generalized, for continuity); ``--oracle`` adds ground-truth
correspondence runs (the back end's ceiling). Prints one table row per (scene, rig, mode):
the mean and worst over the seeds of the SE(3)-aligned ATE (% of the path) beside the keypoint
odometry's alone on the same frames (the sparse core), the Sim(3)
scale error, PSNR on keyframes and on non-keyframes, depth L1 (over every pixel the map renders, then on
those its confidence marks measured, and their share) and seconds; then, per scene
and rig, JDSA on vs off. Everything lands in ``OUT/ablation.json``.
"""

import argparse
import json
from importlib import resources
from pathlib import Path

import numpy as np
import warp as wp

from mcgs_warp.data.synthetic import generate
from mcgs_warp.rig import load_rig
from mcgs_warp.system.config import load_run_config
from mcgs_warp.system.run import run_sequence

MODES = {  # mode: (depth written, JDSA, correspondences)
    "rgb": ("none", True, "estimated"),
    "mono": ("mono", True, "estimated"),
    "mono-nojdsa": ("mono", False, "estimated"),
    "exact": ("exact", True, "estimated"),
    "rgb-sparse": ("none", True, "none"),
    "exact-sparse": ("exact", True, "none"),
    "rgb-oracle": ("none", True, "ground-truth"),
    "exact-oracle": ("exact", True, "ground-truth"),
}


def rig_for(scene: str, name: str):
    """The rig of ``scene`` (None: its default), the front and back pair, or its first camera."""
    if name == "default":
        return None
    if name == "front_back":
        return load_rig(resources.files("mcgs_warp.configs") / "rig_front_back.yaml")
    if name == "one":
        from mcgs_warp.data.synthetic import RIG_CONFIG, STREET_RIG, synthetic_rig

        return synthetic_rig(1, STREET_RIG if scene == "street" else RIG_CONFIG)
    raise SystemExit(f"--rigs: expected default, front_back or one, got {name!r}")


def run_one(out: Path, scene: str, seed: int, mode: str, rig: str, args, realism: str, prior: str) -> dict:
    depth, jdsa, corr = MODES[mode]
    tag = f"{scene}_s{seed}_{rig}_{realism}_{depth}{'_' + prior if depth == 'mono' else ''}"
    data = out / "data" / tag
    if not (data / "timestamps.txt").is_file():
        generate(data, n_frames=args.frames, seed=seed, device=args.device, progress=False, depth=depth, rig=rig_for(scene, rig), realism=realism, mono_prior=prior, scene=scene)
    cfg = load_run_config(None)
    cfg.tracking.correspondences = corr
    if corr == "none":
        cfg.tracking.keypoint_weight = 1.0  # the keypoint tracks are all there is
    run_dir = out / "runs" / f"{tag}_{mode}"
    m = run_sequence(data, run_dir, cfg, jdsa=jdsa, device=args.device, progress=False)
    print(f"done: {scene} seed {seed} {rig} {mode}: SE(3) ATE {m['ate_se3_percent_of_path']:.3f} % of path, scale {m['sim3_scale']:.4f}, {m['psnr_db']:.1f} dB ({m['seconds_total']:.0f} s)", flush=True)
    return {"scene": scene, "seed": seed, "rig": rig, "mode": mode, "realism": realism, "prior": prior, **m}


def summary(rows, scene, rig, mode):
    sel = [r for r in rows if (r["scene"], r["rig"], r["mode"]) == (scene, rig, mode)]
    if not sel:
        return None
    ate = np.array([r["ate_se3_percent_of_path"] for r in sel])
    odo = np.array([r.get("ate_odometry_se3_percent_of_path") if r.get("ate_odometry_se3_percent_of_path") is not None else np.nan for r in sel])
    scale = np.array([abs(r["sim3_scale"] - 1) for r in sel])
    psnr = np.array([r["psnr_db"] for r in sel])
    held = np.array([r["psnr_nonkeyframe_db"] if r["psnr_nonkeyframe_db"] is not None else np.nan for r in sel])
    l1 = np.array([r["depth_l1_m"] if r["depth_l1_m"] is not None else np.nan for r in sel])
    l1m = np.array([r.get("depth_l1_measured_m") if r.get("depth_l1_measured_m") is not None else np.nan for r in sel])
    frac = np.array([r.get("depth_measured_fraction") if r.get("depth_measured_fraction") is not None else np.nan for r in sel])
    secs = np.array([r["seconds_total"] for r in sel])
    return {"n": len(sel), "ate": (ate.mean(), ate.max()), "odo": (np.nanmean(odo) if np.isfinite(odo).any() else np.nan, np.nanmax(odo) if np.isfinite(odo).any() else np.nan), "scale": (scale.mean(), scale.max()), "psnr": (psnr.mean(), psnr.min()), "held": (np.nanmean(held), np.nanmin(held)), "l1": (np.nanmean(l1), np.nanmax(l1)), "l1m": (np.nanmean(l1m), np.nanmax(l1m)), "frac": (np.nanmean(frac), np.nanmin(frac)), "s": (secs.mean(), secs.max())}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["street", "indoor"], choices=["street", "indoor", "room"],
                        help="street, indoor (worlds drawn from the seed) and room (the built-in room; the seed re-draws its objects)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[11, 12, 13], help="held-out seeds (nothing was tuned on them)")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--modes", nargs="+", default=["rgb", "mono", "mono-nojdsa", "exact"], choices=list(MODES))
    parser.add_argument("--rigs", nargs="+", default=["default"], choices=["default", "front_back", "one"])
    parser.add_argument("--realism", default="camera", choices=["camera", "none"])
    parser.add_argument("--room", action="store_true", help="also the built-in room at seed 0, clean images, smooth prior (continuity)")
    parser.add_argument("--oracle", action="store_true", help="also ground-truth correspondences (rgb-oracle, exact-oracle)")
    parser.add_argument("--out", default="out/ablation")
    parser.add_argument("--device", default=None)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    out = Path(args.out)
    modes = args.modes + (["rgb-oracle", "exact-oracle"] if args.oracle else [])
    rows = []
    for scene in args.scenes:
        for rig in args.rigs:
            for mode in modes:
                if rig != "default" and not mode.startswith("mono"):
                    continue  # the other rigs are there for the prior
                for seed in args.seeds:
                    rows.append(run_one(out, scene, seed, mode, rig, args, args.realism, "realistic"))
    if args.room:
        for mode in modes:
            rows.append(run_one(out, "room", 0, mode, "default", args, "none", "smooth"))
    out.mkdir(parents=True, exist_ok=True)
    (out / "ablation.json").write_text(json.dumps(rows, indent=2))
    print()
    print(f"{args.frames} frames, seeds {args.seeds}, --realism {args.realism}, realistic mono prior; mean / worst over the seeds")
    print()
    print("| scene | rig | mode | SE(3) ATE % of path | odometry alone % of path | Sim(3) scale error % | PSNR dB | PSNR non-keyframes dB | depth L1 m | depth L1 measured m | measured share % | s |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    keys = sorted({(r["scene"], r["rig"], r["mode"]) for r in rows}, key=lambda k: (k[0], k[1], modes.index(k[2])))
    for scene, rig, mode in keys:
        s = summary(rows, scene, rig, mode)
        print(f"| {scene} | {rig} | {mode} | {s['ate'][0]:.3f} / {s['ate'][1]:.3f} | {s['odo'][0]:.3f} / {s['odo'][1]:.3f} | {100 * s['scale'][0]:.2f} / {100 * s['scale'][1]:.2f} | {s['psnr'][0]:.1f} / {s['psnr'][1]:.1f} | "
              f"{s['held'][0]:.1f} / {s['held'][1]:.1f} | {s['l1'][0]:.3f} / {s['l1'][1]:.3f} | {s['l1m'][0]:.3f} / {s['l1m'][1]:.3f} | {100 * s['frac'][0]:.0f} / {100 * s['frac'][1]:.0f} | {s['s'][0]:.0f} / {s['s'][1]:.0f} |")
    print()
    for scene, rig in sorted({(k[0], k[1]) for k in keys}):
        on, off = summary(rows, scene, rig, "mono"), summary(rows, scene, rig, "mono-nojdsa")
        if on and off:
            print(f"{scene} {rig}: JDSA on vs off, mean SE(3) ATE {on['ate'][0]:.3f} vs {off['ate'][0]:.3f} % ({100 * (1 - on['ate'][0] / off['ate'][0]):+.0f} %), "
                  f"depth L1 {on['l1'][0]:.3f} vs {off['l1'][0]:.3f} m ({100 * (1 - on['l1'][0] / off['l1'][0]):+.0f} %)")
