#!/usr/bin/env bash
# Results v6 (docs/RESULTS.md) on one machine with one GPU (an NVIDIA H100 or H200 with 16 CPU cores):
# results v5's recipe (gpu_results_v5.sh: 8 tasks x 25 demos, refinements merged, batch 192, 1,200
# steps, --rotation-bins 360 --rotation-sigma 2, 50 seeds per task, 2 x 10 held-out insertion demos)
# with half of every task's draws taken from its keyframe-start samples (`rvt2 train --start-share 0.5`),
# then the same with each task's first 10 demos only (`--episodes-per-task 10`, run v6_10), trained
# while the first model is evaluated, and evaluated on 25 seeds per task (EVAL_EPISODES_10).
#
# On a one-GPU workstation with rvt2 and its simulator installed: `bash scripts/offline-gpu-host/gpu_results_v6.sh all`.
# On a GPU machine without network access, one command per step: `stash` carrying each .gpu/site.part.*
# piece but the last, `start` carrying the last piece and .gl (everything runs in the background), then
# `collect` (waits up to WAIT_S seconds and packs whatever reports exist into results.tgz) until the log
# says the chain is done.
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
export WORKERS=${WORKERS:-14}
onebox=scripts/offline-gpu-host/gpu_onebox.sh
self=scripts/offline-gpu-host/$(basename "$0")
COMPILE=${COMPILE---compile}          # a dry run on a CPU: COMPILE= STEPS=8 EVAL_EPISODES=1 (and gpu_onebox.sh's settings)
export STEPS=${STEPS:-1200}
TRAIN=${TRAIN:---rotation-bins 360 --rotation-sigma 2 --start-share 0.5}
RUN=${RUN:-v6}
export HELDOUT_TASKS=${HELDOUT_TASKS:-"insert_peg plug_charger"} HELDOUT_EPISODES=${HELDOUT_EPISODES:-10}
W=${W:-/tmp/w}

case ${1:-} in
  stash) bash $onebox stash ;;
  start)
    bash $onebox stash setup
    bash $onebox bg chain "$self" chain ;;  # in the background: a command ends after 10 minutes
  chain)
    bash $onebox record heldout merged
    RUN=$RUN DATA=$W/demos_merged TRAIN_ARGS="$COMPILE $TRAIN" bash $onebox train
    # the 10-demo model trains on the GPU while the 25-demo one is evaluated (simulators on the CPUs)
    RUN=${RUN}_10 DATA=$W/demos_merged TRAIN_ARGS="$COMPILE $TRAIN --episodes-per-task 10" bash $onebox train \
      > "$W/train_${RUN}_10.out" 2>&1 &
    RUN=$RUN OFFLINE_DEMOS=$W/heldout_merged bash $onebox eval offline || echo "evaluating $RUN failed"
    wait || echo "training ${RUN}_10 failed: $W/train_${RUN}_10.out"
    RUN=${RUN}_10 EVAL_EPISODES=${EVAL_EPISODES_10:-25} OFFLINE_DEMOS=$W/heldout_merged bash $onebox eval offline ;;
  collect)
    WAIT_S=${WAIT_S:-540} bash $onebox wait chain || true
    RUNS="$RUN ${RUN}_10" bash $onebox results ;;
  all) bash $onebox setup && bash "$self" chain && RUNS="$RUN ${RUN}_10" bash $onebox results ;;
  *) echo "usage: $0 stash|start|collect|all" >&2; exit 2 ;;
esac
