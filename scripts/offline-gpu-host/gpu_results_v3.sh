#!/usr/bin/env bash
# Results v3 (docs/RESULTS.md) on one machine with one GPU (measured on an NVIDIA H200, 141 GB, with 16
# CPU cores): record 8 tasks x 25 demos and 8 x 5 held-out demos (seeds 30000+) with the collision-flag
# rule v3, annotate a second copy with the expert's alignment refinements merged (--merge-refinements 30),
# train the paper configuration on each (batch 192, 1,200 steps, one after the other: two do not fit on
# one GPU together), and evaluate each closed loop on seeds 10000-10049 and offline on the held-out demos.
# While the first model trains, the simulator cores run the oracle on the same seeds and replay results
# v2's recorded predictions through today's executor (`rvt2 eval --replay`).
#
# On a one-GPU workstation with rvt2 and its simulator installed: `bash scripts/offline-gpu-host/gpu_results_v3.sh all`.
# On a GPU machine without network access (pack_gpu_wheels.sh, gpu_onebox.sh beside this script), one
# command per step: `stash` carrying each .gpu/site.part.* piece but the last, then `start` carrying the
# last piece and .gl, then `collect` until it reports everything (each waits up to 9 minutes).
# `start2` / `collect2` (a second machine): the merged model again after the merge rule learned to keep
# turns in place (8 tasks x 25 demos, 1,200 steps, 30 evaluation seeds per task).
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
export WORKERS=${WORKERS:-14}
onebox=scripts/offline-gpu-host/gpu_onebox.sh
self=scripts/offline-gpu-host/$(basename "$0")
COMPILE=${COMPILE---compile}          # a dry run on a CPU: COMPILE= STEPS=8 EVAL_EPISODES=1 (and gpu_onebox.sh's settings)
export STEPS=${STEPS:-1200}
W=${W:-/tmp/w}

next() {  # next RUN DATA [EVAL_RUN EVAL_OFFLINE_DEMOS]: train RUN in the background while EVAL_RUN is evaluated
  RUN=$1 DATA=$2 TRAIN_ARGS=$COMPILE START_WAIT=1 bash $onebox bg "$1" train
  if [ -n "${3:-}" ]; then RUN=$3 OFFLINE_DEMOS=$4 WORKERS=10 bash $onebox eval offline; fi  # the training keeps its cores
  WAIT_S=100000 bash $onebox wait "$1"
}

case ${1:-} in
  stash) bash $onebox stash ;;
  start)
    bash $onebox stash setup
    bash $onebox bg chain "$self" chain ;;  # in the background: a command ends after 10 minutes
  chain)
    bash $onebox record heldout merged
    RUN=kept DATA=$W/demos TRAIN_ARGS=$COMPILE START_WAIT=1 bash $onebox bg kept train
    WORKERS=10 bash $onebox oracle replay
    WAIT_S=100000 bash $onebox wait kept
    next merged "$W/demos_merged" kept "$W/heldout"
    RUN=merged OFFLINE_DEMOS=$W/heldout_merged bash $onebox eval offline ;;
  start2)  # a second machine: the merged-refinements model again, with the rule that keeps turns in place
    bash $onebox stash setup
    bash $onebox bg chain "$self" chain2 ;;
  chain2)
    bash $onebox record merged
    RUN=merged2 DATA=$W/demos_merged TRAIN_ARGS=$COMPILE bash $onebox train
    RUN=merged2 EVAL_EPISODES=${EVAL_EPISODES_2:-30} bash $onebox eval ;;
  collect2)
    WAIT_S=${WAIT_S:-540} bash $onebox wait chain || true
    RUNS=merged2 bash $onebox results ;;
  collect)
    WAIT_S=${WAIT_S:-540} bash $onebox wait chain || true
    RUNS="kept merged" bash $onebox results ;;
  all) bash $onebox setup && bash "$self" chain && bash "$self" collect ;;
  *) echo "usage: $0 stash|start|collect|start2|collect2|all" >&2; exit 2 ;;
esac
