#!/usr/bin/env bash
# Results v8 (docs/RESULTS.md) on one machine with one GPU (an NVIDIA H100 or H200 with 16 CPU cores):
# results v6's recipe (gpu_results_v6.sh: 8 tasks x 25 demos, refinements merged, batch 192, 1,200 steps,
# --rotation-bins 360 --rotation-sigma 2 --start-share 0.5, 50 seeds per task, 2 x 10 held-out insertion
# demos) trained with `--aim-held --coarse-action-features`: once it holds the peg, the policy aims insert_peg's
# aim offset (12 cm along the peg, tasks/insert_peg.toml) instead of the TCP, and its heads also read stage 1.
# Set TRAIN to add or drop options. As in v6's script, the 10-demo model (`--episodes-per-task 10`) trains
# on the GPU while the 25-demo model is evaluated, and is evaluated on EVAL_EPISODES_10 (25) seeds per task;
# TEN= leaves it out.
#
# On a one-GPU workstation with rvt2 and its simulator installed: `bash scripts/offline-gpu-host/gpu_results_v8.sh all`.
# On a GPU machine without network access, one command per step: `stash` carrying each .gpu/site.part.*
# piece but the last, `start` carrying the last piece and .gl (everything runs in the background), then
# `collect` (waits up to WAIT_S seconds and packs whatever reports exist into results.tgz) until the log
# says the chain is done.
#
# The 2-task proxy (insert_peg and plug_charger, 25 demos each, refinements merged, no held-out demos),
# for a machine with less time: `TASKS="insert_peg plug_charger" STEPS=600 EVAL_EPISODES=30 RUN=v8_proxy`
# with `proxy-start` in place of `start` (and `proxy` in place of `all`), then `collect` as above.
#
# insert_peg alone with 10 held-out demos (eight times the 8-task model's training per task):
# `export TASKS=insert_peg HELDOUT_TASKS=insert_peg TEN= RUN=v8_peg`, then `all` (or `start`, `collect`).
#
# STRAIGHT=1 also evaluates the 25-demo model pushed straight (`rvt2 eval --no-insertion-search`, report
# eval_${RUN}_straight) beside its evaluation with the insertion search: results v9 (gpu_results_v9.sh).
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
export WORKERS=${WORKERS:-14}
onebox=scripts/offline-gpu-host/gpu_onebox.sh
self=scripts/offline-gpu-host/$(basename "$0")
COMPILE=${COMPILE---compile}          # a dry run on a CPU: COMPILE= STEPS=8 EVAL_EPISODES=1 (and gpu_onebox.sh's settings)
export STEPS=${STEPS:-1200}
TRAIN=${TRAIN:---rotation-bins 360 --rotation-sigma 2 --start-share 0.5 --aim-held --coarse-action-features}
RUN=${RUN:-v8}
TEN=${TEN-1}
STRAIGHT=${STRAIGHT-}
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
    if [ -n "$TEN" ]; then  # the 10-demo model trains on the GPU while the 25-demo one is evaluated (simulators on the CPUs)
      RUN=${RUN}_10 DATA=$W/demos_merged TRAIN_ARGS="$COMPILE $TRAIN --episodes-per-task 10" bash $onebox train \
        > "$W/train_${RUN}_10.out" 2>&1 &
      ten=$!
    fi
    RUN=$RUN OFFLINE_DEMOS=$W/heldout_merged bash $onebox eval offline || echo "evaluating $RUN failed"
    if [ -n "$STRAIGHT" ]; then
      RUN=$RUN EVAL_NAME=${RUN}_straight EVAL_ARGS=--no-insertion-search bash $onebox eval \
        || echo "evaluating $RUN pushed straight failed"
    fi
    if [ -n "$TEN" ]; then
      wait "$ten" || echo "training ${RUN}_10 failed: $W/train_${RUN}_10.out"
      RUN=${RUN}_10 EVAL_EPISODES=${EVAL_EPISODES_10:-25} OFFLINE_DEMOS=$W/heldout_merged bash $onebox eval offline \
        || echo "evaluating ${RUN}_10 failed"
    fi ;;
  proxy-start)
    bash $onebox stash setup
    bash $onebox bg chain "$self" proxy-chain ;;
  proxy-chain)
    bash $onebox record merged
    RUN=$RUN DATA=$W/demos_merged TRAIN_ARGS="$COMPILE $TRAIN" bash $onebox train
    RUN=$RUN bash $onebox eval ;;
  proxy) bash $onebox setup && bash "$self" proxy-chain && RUNS=$RUN bash $onebox results ;;
  collect)
    WAIT_S=${WAIT_S:-540} bash $onebox wait chain || true
    RUNS="$RUN ${RUN}_10 ${RUN}_straight" bash $onebox results ;;
  all) bash $onebox setup && bash "$self" chain && RUNS="$RUN ${RUN}_10 ${RUN}_straight" bash $onebox results ;;
  *) echo "usage: $0 stash|start|proxy-start|collect|all|proxy" >&2; exit 2 ;;
esac
