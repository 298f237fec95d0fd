#!/usr/bin/env bash
# The commands behind docs/RESULTS.md, in order. Steps 1-3 and 5 run on the CPU machine (make setup
# first); step 4 runs where a GPU is (see below). DATA defaults to data/ in the repository (git-ignored).
set -euo pipefail
DATA=${DATA:-data}
TASKS="insert_peg plug_charger place_sphere lift_peg_upright stack_cube pick_cube push_cube pull_cube"
step=${1:-all}

if [[ $step == all || $step == record ]]; then          # 1. 25 successful expert demos per task (~10 min, 2 cores)
  for t in $TASKS; do rvt2 record --task "$t" --episodes 25 --workers 2 --out "$DATA/demos25"; done
fi
if [[ $step == all || $step == keyframes ]]; then       # 2. keyframes and training samples (~1 min)
  rvt2 extract-keyframes "$DATA/demos25"
fi
if [[ $step == all || $step == pack ]]; then            # 3. one file with the samples the GPU trains on (370 MB)
  rvt2 pack-samples "$DATA/demos25" --keyframe-starts-only --out "$DATA/samples25.safetensors"
fi
if [[ $step == train ]]; then                           # 4. on a GPU machine with rvt2 installed (H200: 10.4 + 5.2 + 21 min)
  common=(--data "$DATA/samples25.safetensors" --config rvt2 --compile --render-backend torch --val-episodes 0)
  rvt2 train "${common[@]}" --steps 8000 --out "$DATA/runs/demos25"
  rvt2 train "${common[@]}" --steps 4000 --episodes-per-task 10 --out "$DATA/runs/demos10"
  rvt2 train "${common[@]}" --steps 16000 --out "$DATA/runs/demos25_16k"    # 21 min
  # Our lent GPU machine has no rvt2 install and a 64 MiB limit each way: scripts/gpu_train.sh ran these
  # same two commands there, and scripts/gpu_checkpoint.py carried the weights back as float16.
fi
if [[ $step == all || $step == eval ]]; then            # 5. closed loop on seeds 10000-10024, 2 cores
  rvt2 eval --checkpoint "$DATA/runs/demos25" --episodes 25 --workers 2 --oracle --out "$DATA/evals/demos25"
  rvt2 eval --checkpoint "$DATA/runs/demos10" --episodes 25 --workers 2 --out "$DATA/evals/demos10"
  rvt2 eval --checkpoint "$DATA/runs/demos25_16k" --episodes 25 --workers 2 --out "$DATA/evals/demos25_16k"
  python -m benchmarks.record_bench --tasks "${TASKS// /,}" --first-seed 10000 --seeds 25 --episodes 0 \
    --json "$DATA/expert_eval_seeds.json"
  python -m benchmarks.results_table --policy "25 demos=$DATA/evals/demos25" --policy "10 demos=$DATA/evals/demos10" \
    --policy "25 demos, 16k steps=$DATA/evals/demos25_16k" --oracle "$DATA/evals/demos25" \
    --expert "$DATA/expert_eval_seeds.json" --chart docs/results.png --json benchmarks/results/results.json
fi
