#!/usr/bin/env bash
# Results v4 (docs/RESULTS.md) on one machine with one GPU (an NVIDIA H100 or H200 with 16 CPU cores):
# record 8 tasks x 25 demos with rvt2's own insert_peg expert (rvt2cli/record/experts.py) and 2 x 10
# held-out insertion demos (seeds 30000+), merge the alignment refinements (--merge-refinements 30, turns
# kept), train the paper configuration (batch 192, 1,200 steps, as v3), evaluate closed loop on seeds
# 10000-10049 and offline on the held-out demos.
#
# On a one-GPU workstation with rvt2 and its simulator installed: `bash scripts/offline-gpu-host/gpu_results_v4.sh all`.
# On a GPU machine without network access (pack_gpu_wheels.sh, gpu_onebox.sh beside this script), one
# command per step: `stash` carrying each .gpu/site.part.* piece but the last, then `start` carrying the
# last piece and .gl (recording and training run in the background), then `evaluate` (waits for the
# training, then evaluates with the executor of the tree it runs from) until it reports everything.
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
export WORKERS=${WORKERS:-14}
onebox=scripts/offline-gpu-host/gpu_onebox.sh
self=scripts/offline-gpu-host/$(basename "$0")
COMPILE=${COMPILE---compile}          # a dry run on a CPU: COMPILE= STEPS=8 EVAL_EPISODES=1 (and gpu_onebox.sh's settings)
export STEPS=${STEPS:-1200}
export ROTATION=${ROTATION:-}         # rotation options of rvt2 train (results v5: --rotation-bins 360 --rotation-sigma 2)
export RUN=${RUN:-v4} HELDOUT_TASKS=${HELDOUT_TASKS:-"insert_peg plug_charger"} HELDOUT_EPISODES=${HELDOUT_EPISODES:-10}
W=${W:-/tmp/w}

case ${1:-} in
  stash) bash $onebox stash ;;
  start)
    bash $onebox stash setup
    bash $onebox bg chain "$self" chain ;;  # in the background: a command ends after 10 minutes
  chain)
    bash $onebox record heldout merged
    DATA=$W/demos_merged TRAIN_ARGS="$COMPILE $ROTATION" bash $onebox train ;;
  evaluate)
    WAIT_S=${WAIT_S:-540} bash $onebox wait chain
    OFFLINE_DEMOS=$W/heldout_merged bash $onebox eval offline results ;;
  all) bash $onebox setup && bash "$self" chain && OFFLINE_DEMOS=$W/heldout_merged bash $onebox eval offline results ;;
  *) echo "usage: $0 stash|start|evaluate|all" >&2; exit 2 ;;
esac
