"""How the system scales with sequence length: the closed-loop synthetic room, or a street drive.

    python benchmarks/scaling.py [--scene room|street] [--lengths 40 160 640] [--depth exact] [--out out/scaling]

``--scene street`` (lengths 50 150 300, RGB only by default): ``mcgs-slam synth --scene street
--depth none --frames N``, 1 m per frame at 10 m/s (every frame is a keyframe), the road as long as
the drive. The room:

For each length N: ``mcgs-slam synth --trajectory loop --frames N`` (one loop back to its start
at 0.55 m/s, the same distance per frame at every length: the full 35.5 m room loop from 640
frames, a shorter loop below, whose turns are tighter: 9 degrees per frame at 40 frames against
2.65 on the full loop), then a full run in a fresh process (so peak memory is per run). Prints per
length: keyframes, seconds per frame, peak resident memory, global-BA seconds, SE(3)-aligned
ATE, and the end-to-start drift (error of the relative pose between the first and the last
keyframe, which a closed loop makes observable) before and after global BA.

The targets of issue 12 (seconds per frame grows <= 1.5x from 40 to 640 frames, <= 4 GB at
640, global BA over 300 keyframes <= 2 GB and <= 120 s, drift halved by global BA) are what
this table is for. Loop edges: revisit candidates global BA confirmed / examined
(:meth:`mcgs_warp.ba.graph.FactorGraph.close_loops`).
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, resource, sys, time
import numpy as np
import warp as wp
wp.config.log_level = wp.LOG_WARNING
from mcgs_warp.data import open_sequence
from mcgs_warp.system.config import RunConfig
from mcgs_warp.system.outputs import write_outputs
from mcgs_warp.system.slam import SLAM, Progress

data, out = sys.argv[1], sys.argv[2]
seq = open_sequence(data)
t0 = time.perf_counter()
slam = SLAM(seq, RunConfig(), progress=Progress(False))
result = slam.run()
m = write_outputs(out, slam, result, time.perf_counter() - t0)
gt = seq.groundtruth
idx = [int(np.argmin(np.abs(gt.timestamps - t))) for t in (slam.buf.timestamps[0], slam.buf.timestamps[-1])]
rel_gt = np.linalg.inv(gt.poses[idx[0]]) @ gt.poses[idx[1]]

def drift(T):
    rel = np.linalg.inv(T[0]) @ T[-1]
    return float(np.linalg.norm(rel[:3, 3] - rel_gt[:3, 3]))

m["drift_before_global_ba_m"] = drift(slam.poses_before_global_ba)
m["drift_after_global_ba_m"] = drift(slam.buf.get_poses())
m["loops_confirmed"] = slam.backend.confirmed_loops
m["loops_examined"] = len(slam.backend.loops)
m["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(m))
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="room", choices=("room", "street"), help="room: the closed loop; street: a drive down the street")
    parser.add_argument("--lengths", type=int, nargs="+", default=None, help="frames (default: room 40 160 640, street 50 150 300)")
    parser.add_argument("--depth", default=None, choices=("exact", "mono", "none"), help="depth written (default: room exact, street none)")
    parser.add_argument("--out", default="out/scaling")
    args = parser.parse_args()
    street = args.scene == "street"
    lengths = args.lengths or ([50, 150, 300] if street else [40, 160, 640])
    depth = args.depth or ("none" if street else "exact")
    out = Path(args.out)
    rows = []
    for n in lengths:
        data = out / (f"street_{depth}_{n}" if street else f"loop_{n}")
        if not (data / "timestamps.txt").is_file():
            scene = ["--scene", "street"] if street else ["--trajectory", "loop", "--realism", "none"]
            subprocess.run([sys.executable, "-m", "mcgs_warp", "synth", "--out", str(data), "--frames", str(n), "--depth", depth, *scene], check=True, capture_output=True)
        res = subprocess.run([sys.executable, "-c", CHILD, str(data), str(out / f"run_{data.name}")], check=True, capture_output=True, text=True)
        m = json.loads(res.stdout.strip().splitlines()[-1])
        rows.append((n, m))
        print(f"done: {n} frames ({m['seconds_total']:.0f} s)", flush=True)
    print()
    print("| frames | keyframes | s / frame | peak RSS MB | global BA s | SE(3) ATE mm | % of path | drift before GBA mm | drift after GBA mm | loop edges |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n, m in rows:
        print(f"| {n} | {m['n_keyframes']} | {m['seconds_total'] / n:.2f} | {m['peak_rss_mb']:.0f} | {m['seconds'].get('global_ba', 0):.1f} | {1000 * m['ate_se3_rmse_m']:.1f} | {100 * m['ate_se3_rmse_m'] / m['path_length_m']:.2f} | {1000 * m['drift_before_global_ba_m']:.1f} | {1000 * m['drift_after_global_ba_m']:.1f} | {m['loops_confirmed']}/{m['loops_examined']} |")
    if len(rows) > 1:
        (n0, a), (n1, b) = rows[0], rows[-1]
        print(f"\n{args.scene}: seconds per frame at {n1} frames / at {n0}: {(b['seconds_total'] / n1) / (a['seconds_total'] / n0):.2f}x; peak RSS {b['peak_rss_mb'] / a['peak_rss_mb']:.2f}x")


if __name__ == "__main__":
    main()
