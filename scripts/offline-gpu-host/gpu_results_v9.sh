#!/usr/bin/env bash
# Results v9's closed loop (docs/RESULTS.md) on one machine with one GPU (an NVIDIA H100 or H200 with 16 CPU
# cores): results v8's one-task recipe (gpu_results_v8.sh with TASKS=insert_peg: 25 demos, refinements merged,
# batch 192, 1,200 steps, --rotation-bins 360 --rotation-sigma 2 --start-share 0.5 --aim-held
# --coarse-action-features, 10 held-out demos scored offline), and the model evaluated closed loop on 50 seeds
# twice: with the executor's insertion search (rvt2 eval's default) and pushed straight
# (`--no-insertion-search`, report eval_${RUN}_straight). TASKS, HELDOUT_TASKS, STEPS, TRAIN and RUN as in
# gpu_results_v8.sh: the 8-task model is `TASKS= HELDOUT_TASKS="insert_peg plug_charger" RUN=v9` (23 minutes
# on one H200 before its second evaluation, against 11 for insert_peg alone on one H100).
#
# It is gpu_results_v8.sh with these settings and STRAIGHT=1, and takes its steps: on a one-GPU workstation
# with rvt2 and its simulator installed `bash scripts/offline-gpu-host/gpu_results_v9.sh all`; on a GPU
# machine without network access `stash` (x3), `start`, then `collect` until the log says the chain is done.
set -euo pipefail
export TASKS=${TASKS-insert_peg}
[ -n "$TASKS" ] || unset TASKS       # empty: gpu_onebox.sh's eight tasks
export HELDOUT_TASKS=${HELDOUT_TASKS:-insert_peg} RUN=${RUN:-v9_peg} TEN=${TEN-} STRAIGHT=1
exec bash "$(dirname "$0")/gpu_results_v8.sh" "$@"
