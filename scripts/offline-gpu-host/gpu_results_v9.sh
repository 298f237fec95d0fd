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
# On a one-GPU workstation with rvt2 and its simulator installed: `bash scripts/offline-gpu-host/gpu_results_v9.sh all`.
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
TRAIN=${TRAIN:---rotation-bins 360 --rotation-sigma 2 --start-share 0.5 --aim-held --coarse-action-features}
RUN=${RUN:-v9_peg}
export TASKS=${TASKS-insert_peg}
[ -n "$TASKS" ] || unset TASKS       # empty: gpu_onebox.sh's eight tasks
export HELDOUT_TASKS=${HELDOUT_TASKS:-insert_peg} HELDOUT_EPISODES=${HELDOUT_EPISODES:-10}
W=${W:-/tmp/w}

case ${1:-} in
  stash) bash $onebox stash ;;
  start)
    bash $onebox stash setup
    bash $onebox bg chain "$self" chain ;;  # in the background: a command ends after 10 minutes
  chain)
    bash $onebox record heldout merged
    RUN=$RUN DATA=$W/demos_merged TRAIN_ARGS="$COMPILE $TRAIN" bash $onebox train
    RUN=$RUN OFFLINE_DEMOS=$W/heldout_merged bash $onebox eval offline || echo "evaluating $RUN failed"
    RUN=$RUN EVAL_NAME=${RUN}_straight EVAL_ARGS=--no-insertion-search bash $onebox eval \
      || echo "evaluating $RUN pushed straight failed" ;;
  collect)
    WAIT_S=${WAIT_S:-540} bash $onebox wait chain || true
    RUNS="$RUN ${RUN}_straight" bash $onebox results ;;
  all) bash $onebox setup && bash "$self" chain && RUNS="$RUN ${RUN}_straight" bash $onebox results ;;
  *) echo "usage: $0 stash|start|collect|all" >&2; exit 2 ;;
esac
