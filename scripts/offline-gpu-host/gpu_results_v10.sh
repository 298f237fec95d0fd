#!/usr/bin/env bash
# Results v10 (docs/RESULTS.md) on one machine with two GPUs (2 x NVIDIA H200, 32 CPU cores): the 8-task
# model of results v8's recipe (8 tasks x 25 demos, refinements merged, batch 192, --rotation-bins 360
# --rotation-sigma 2 --start-share 0.5 --aim-held --coarse-action-features, 2 x 10 held-out insertion demos
# scored offline), trained twice as long (2,400 steps, DDP over both GPUs) with the two insertions drawn four
# times as often as each other task (`--task-weights insert_peg=4,plug_charger=4`: a quarter of the draws
# each, and each other task 171 of v8's 150 steps' worth), then evaluated closed loop with the insertion
# search on 50 seeds per task.
#
# It is gpu_results_v8.sh with these settings; its steps are v8's: on a two-GPU workstation with rvt2 and
# its simulator installed `bash scripts/offline-gpu-host/gpu_results_v10.sh all`; on a GPU machine without
# network access `stash` (x3), `start`, then `collect` until the log says the chain is done. On one GPU,
# NPROC=1 (about 1.7 times as long).
set -euo pipefail
export NPROC=${NPROC:-2} WORKERS=${WORKERS:-30} STEPS=${STEPS:-2400} RUN=${RUN:-v10} TEN=${TEN-}
export TRAIN=${TRAIN:-"--rotation-bins 360 --rotation-sigma 2 --start-share 0.5 --aim-held --coarse-action-features --task-weights insert_peg=4,plug_charger=4"}
exec bash "$(dirname "$0")/gpu_results_v8.sh" "$@"
