"""Run the system on a EuRoC MAV sequence (stereo pair as a 2-camera rig).

    python examples/run_euroc.py /path/to/MH_01_easy --out out/euroc [--frames 200] [--config CFG]

EuRoC has no depth: depth starts constant and the stereo baseline (cross-view
edges) gives the metric scale. ``--frames`` keeps the first N frames (a quick look).
The estimate is compared with ``state_groundtruth_estimate0`` when present.
"""

import argparse
import json

import warp as wp

from mcgs_warp.data import open_sequence
from mcgs_warp.data.sequence import Sequence
from mcgs_warp.system.config import load_run_config
from mcgs_warp.system.outputs import write_outputs
from mcgs_warp.system.slam import SLAM, Progress


class FirstFrames(Sequence):
    def __init__(self, seq, n):
        self.seq, self.rig, self.groundtruth, self.name = seq, seq.rig, seq.groundtruth, seq.name
        self.timestamps = seq.timestamps[:n]

    def load_frame(self, k):
        return self.seq[k]


if __name__ == "__main__":
    import time

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", help="EuRoC sequence folder (containing mav0/)")
    parser.add_argument("--out", default="out/euroc")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--config", default=None)
    parser.add_argument("--device", default=None)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    t0 = time.perf_counter()
    seq = open_sequence(args.data)
    if args.frames:
        seq = FirstFrames(seq, args.frames)
    slam = SLAM(seq, load_run_config(args.config), device=args.device, progress=Progress())
    metrics = write_outputs(args.out, slam, slam.run(), time.perf_counter() - t0)
    print(json.dumps(metrics, indent=2))
