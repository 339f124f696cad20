"""A speed claim as the ratio of new to old, run back to back on the same machine.

    python benchmarks/ab.py OLD_REF NEW_REF [--runs 2] [--warmup 0] [--out out/ab] -- COMMAND ...

Checks both revisions out into temporary git worktrees and runs COMMAND in each worktree's root,
alternating (old, new, old, new, ...), so that the machine's drift (this VM's speed moves by up
to 1.7x between hours) falls on both alike. ``{out}`` in COMMAND becomes a fresh folder per run
(OUT/<old|new>_<i>), e.g.

    python benchmarks/ab.py main HEAD -- mcgs-slam run --data ../shared/data/kitti_stereo_excerpt --out {out}

``mcgs-slam`` and ``python`` in COMMAND run the worktree's own code (its folder first on
PYTHONPATH, with the package's ``kernels`` and ``configs`` linked in as an installed package has
them; this environment's dependencies). ``--warmup N`` runs each revision N times first, untimed
(Warp compiles a changed kernel module once; its cache is shared). Prints each run's wall
seconds and, where the run wrote ``{out}/metrics.json``, its quality figures (SE(3) ATE, PSNR on
keyframes and held-out frames, depth against exact depth); then the median time of each
revision and their ratio new/old.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def worktree(ref: str, where: Path) -> Path:
    """A detached worktree of ``ref`` at ``where`` whose ``mcgs_warp`` imports as the installed package does."""
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "--quiet", str(where), ref], check=True)
    for sub in ("kernels", "configs"):
        link = where / "mcgs_warp" / sub
        if not link.exists():
            link.symlink_to(where / sub, target_is_directory=True)
    return where


def command(argv: list[str], tree: Path, out: Path) -> list[str]:
    cmd = [a.replace("{out}", str(out)) for a in argv]
    if cmd[0] == "mcgs-slam":
        cmd = [sys.executable, "-m", "mcgs_warp", *cmd[1:]]
    elif cmd[0] in ("python", "python3"):
        cmd = [sys.executable, *cmd[1:]]
    return cmd


def quality(out: Path) -> str:
    f = out / "metrics.json"
    if not f.is_file():
        return ""
    m = json.loads(f.read_text())
    parts = []
    if m.get("ate_se3_rmse_m") is not None:
        parts.append(f"SE(3) {m['ate_se3_rmse_m']:.4f} m")
    if m.get("psnr_db") is not None:
        held = m.get("psnr_nonkeyframe_db")
        parts.append(f"PSNR {m['psnr_db']:.2f} / {'–' if held is None else f'{held:.2f}'} dB")
    if m.get("depth_l1_m") is not None:
        parts.append(f"depth L1 {m['depth_l1_m']:.3f} m")
    for cam, d in (m.get("depth_vs_exact_per_camera") or {}).items():
        if d.get("median_rel") is not None:
            parts.append(f"{cam} {100 * d['median_rel']:.1f} %")
    return ", ".join(parts)


def main() -> int:
    argv = sys.argv[1:]
    i = argv.index("--") if "--" in argv else len(argv)
    argv, rest = argv[:i], argv[i + 1 :]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], usage="%(prog)s OLD_REF NEW_REF [options] -- COMMAND ...")
    ap.add_argument("old")
    ap.add_argument("new")
    ap.add_argument("--runs", type=int, default=2, help="timed runs of each revision (default 2)")
    ap.add_argument("--warmup", type=int, default=0, help="untimed runs of each revision first (default 0)")
    ap.add_argument("--out", type=Path, default=Path("out/ab"))
    args = ap.parse_args(argv)
    if not rest:
        ap.error("COMMAND missing: put it after --")
    if args.runs < 1 or args.warmup < 0:
        ap.error("--runs must be at least 1 and --warmup at least 0")
    times: dict = {"old": [], "new": []}
    with tempfile.TemporaryDirectory() as tmp:
        trees: dict = {}
        try:
            for side in ("old", "new"):
                trees[side] = worktree(getattr(args, side), Path(tmp) / side)
            for i in range(-args.warmup, args.runs):
                for side in ("old", "new"):
                    tree = trees[side]
                    out = (args.out / f"{side}_{i}").resolve() if i >= 0 else Path(tmp) / f"warmup_{side}_{i}"
                    shutil.rmtree(out, ignore_errors=True)  # no metrics of an earlier run are printed as this one's
                    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
                    cmd = command(rest, tree, out)
                    t0 = time.perf_counter()
                    res = subprocess.run(cmd, cwd=tree, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                    dt = time.perf_counter() - t0
                    if res.returncode != 0:
                        print(f"{side} ({getattr(args, side)}) failed, exit {res.returncode}: {shlex.join(cmd)}\n{res.stderr[-2000:]}", file=sys.stderr)
                        return res.returncode
                    if i < 0:
                        continue
                    times[side].append(dt)
                    print(f"{side} {getattr(args, side)} run {i + 1}: {dt:.1f} s  {quality(out)}", flush=True)
        finally:
            for tree in trees.values():
                subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], capture_output=True)
    old, new = statistics.median(times["old"]), statistics.median(times["new"])
    print(f"median: old {old:.1f} s, new {new:.1f} s; new/old = {new / old:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
