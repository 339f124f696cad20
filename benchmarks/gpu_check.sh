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
cd "$(dirname "$0")/.."
DATA=${1:-../shared/data/kitti_stereo_excerpt}
DEVICE=${DEVICE:-cuda:0}
OUT=${OUT:-out/gpu}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if [ -d .whl ] && ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
if ! python3 -c "import mcgs_warp.kernels" 2>/dev/null; then
  pkg=$(mktemp -d)
  cp -rs "$PWD/mcgs_warp" "$pkg/mcgs_warp"
  ln -s "$PWD/kernels" "$pkg/mcgs_warp/kernels"
  ln -s "$PWD/configs" "$pkg/mcgs_warp/configs"
  export PYTHONPATH=$pkg${PYTHONPATH:+:$PYTHONPATH}
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
python3 -c "import warp as wp; wp.init(); print('warp', wp.__version__, 'devices', wp.get_devices())"

step() {  # step NAME COMMAND...: wall seconds and peak resident memory of one step
  local name=$1; shift
  local t0=$(date +%s.%N)
  /usr/bin/time -f "%M" -o "$OUT/$name.rss" "$@" > "$OUT/$name.log" 2>&1 || { echo "$name failed:"; tail -n 40 "$OUT/$name.log"; return 1; }
  printf '%-8s %7.1f s  peak %.2f GB\n' "$name" "$(echo "$(date +%s.%N) - $t0" | bc)" "$(echo "$(cat "$OUT/$name.rss") / 1048576" | bc -l)"
}

step demo python3 -m mcgs_warp --device "$DEVICE" demo --out "$OUT/demo"
if [ -d "$DATA" ]; then
  step run python3 -m mcgs_warp --device "$DEVICE" run --data "$DATA" --out "$OUT/run"
  python3 - "$OUT/run/metrics.json" <<'PY'
import json, sys
m = json.load(open(sys.argv[1]))
print({k: m.get(k) for k in ("ate_se3_rmse_m", "ate_rmse_m", "sim3_scale", "psnr_db", "psnr_nonkeyframe_db", "tracking_failures", "n_keyframes", "seconds_total")})
PY
  step profile python3 benchmarks/stage_profile.py --data "$DATA" --out "$OUT/profile" --device "$DEVICE"
  sed -n '/| stage/,$p' "$OUT/profile.log"
else
  echo "no sequence at $DATA: the demo alone (copy a real sequence into the checkout, ignored, and pass its path)"
fi
