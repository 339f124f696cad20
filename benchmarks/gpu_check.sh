#!/usr/bin/env bash
# The GPU check, one command for the day a GPU is lent (under 10 minutes on one H100):
# the demo, a real sequence and the stage profile on that sequence, all with --device cuda:0.
#
#   bash benchmarks/gpu_check.sh [DATA]        (DATA: default ../shared/data/kitti_stereo_excerpt)
#
# Environment: DEVICE (default cuda:0), OUT (default out/gpu; $OUT on the device machine).
# Dependencies: the project's, importable (an installed environment, or wheels in .whl/ that it
# installs into /tmp/site, offline). Without an installed package the checkout itself is put on
# the path as the package is laid out when installed (kernels and configs inside mcgs_warp).
# Prints the GPU, each step's wall time and peak memory, the run's metrics and the stage table:
# their figures go into docs/results.md beside the CPU's.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
DATA=$(realpath -m "${1:-$root/../shared/data/kitti_stereo_excerpt}")
DEVICE=${DEVICE:-cuda:0}
OUT=$(realpath -m "${OUT:-$root/out/gpu}")
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if [ -d "$root/.whl" ] && ls "$root"/.whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$root"/.whl/*.whl
  export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
# Run from outside the checkout: its mcgs_warp/ (no kernels inside) would shadow the package.
work=$(mktemp -d)
cd "$work"
if ! python3 -c "import mcgs_warp.kernels" 2>/dev/null; then
  cp -rs "$root/mcgs_warp" "$work/mcgs_warp"
  ln -s "$root/kernels" "$work/mcgs_warp/kernels"
  ln -s "$root/configs" "$work/mcgs_warp/configs"
  export PYTHONPATH=$work${PYTHONPATH:+:$PYTHONPATH}
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
python3 -c "import warp as wp; wp.init(); print('warp', wp.__version__, 'devices', wp.get_devices())"

step() {  # step NAME COMMAND...: wall seconds and peak resident memory of one step
  local name=$1; shift
  python3 - "$OUT/$name.log" "$@" <<'PY' || { echo "$name failed:"; tail -n 40 "$OUT/$name.log"; return 1; }
import os, subprocess, sys, time
log, cmd = sys.argv[1], sys.argv[2:]
t0 = time.perf_counter()
with open(log, "w") as f:
    proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
    _, status, usage = os.wait4(proc.pid, 0)
print(f"{os.path.basename(log)[:-4]:<8} {time.perf_counter() - t0:7.1f} s  peak {usage.ru_maxrss / 1024**2:.2f} GB", flush=True)
sys.exit(os.waitstatus_to_exitcode(status))
PY
}

step demo python3 -m mcgs_warp --device "$DEVICE" demo --out "$OUT/demo"
if [ -d "$DATA" ]; then
  step run python3 -m mcgs_warp --device "$DEVICE" run --data "$DATA" --out "$OUT/run"
  python3 - "$OUT/run/metrics.json" <<'PY'
import json, sys
m = json.load(open(sys.argv[1]))
print({k: m.get(k) for k in ("ate_se3_rmse_m", "ate_rmse_m", "sim3_scale", "psnr_db", "psnr_nonkeyframe_db", "tracking_failures", "n_keyframes", "seconds_total")})
PY
  step profile python3 "$root/benchmarks/stage_profile.py" --data "$DATA" --out "$OUT/profile" --device "$DEVICE"
  sed -n '/| stage/,$p' "$OUT/profile.log"
else
  echo "no sequence at $DATA: the demo alone (copy a real sequence into the checkout, ignored, and pass its path)"
fi
