#!/usr/bin/env bash
# GPU benchmarks on a GPU machine without network access (python3 with CUDA torch, nothing else).
#
# warp-lang and the other libraries are not installed there: pack_gpu_wheels.sh packs them into
# .gpu/site.part.*, which are carried one per transfer into /tmp/w/ (gpu_onebox.sh stash), then:
#   bash scripts/offline-gpu-host/gpu_bench.sh   # unpacks into /tmp/site, runs the CUDA tests and benchmarks
# Results land in $OUT (render.json, policy.json, logs).
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-/tmp/rvt2-bench}
mkdir -p "$OUT" /tmp/site
if [ ! -d /tmp/site/warp ]; then
  cat /tmp/w/site.part.* | xz -d | tar -x -C /tmp/site
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
python3 -c "import torch, warp, bitsandbytes; print('torch', torch.__version__, 'warp', warp.__version__, 'bitsandbytes', bitsandbytes.__version__)" | tee -a "$OUT/gpu.txt"
python3 -m pytest -q -p no:cacheprovider tests/test_render.py tests/test_model.py tests/test_capture.py 2>&1 | tail -3 | tee "$OUT/tests.txt"
python3 -m benchmarks.render_bench --device cuda --json "$OUT/render.json" 2>&1 | tee "$OUT/render.txt"
python3 -m benchmarks.policy_bench --device cuda --json "$OUT/policy.json" "$@" 2>&1 | tee "$OUT/policy.txt"
