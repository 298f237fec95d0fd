#!/usr/bin/env bash
# The models of docs/RESULTS.md v2, on one machine with one GPU (one NVIDIA H200 with 139 GiB, 16 CPU
# cores, no network access). One training at a time (two at batch 192 need 76 + 64 GiB: they do not fit
# together); each model is evaluated while the next one trains. Two parts:
#   part 1: record 8 tasks x 25 demos and 8 x 5 held-out demos (seeds 30000+); time the training loop
#           against its step (benchmarks/loop_bench.py); train the 10-demo model, then the 10-demo
#           front-camera model, then the 25-demo model (seed 0); evaluate each closed-loop on seeds
#           10000-10049 (the front camera's on 25 per task) and offline on the held-out demos, and
#           part of seed 0's evaluation again (are the episodes the same?).
#   part 2: the same recording; the 25-demo model's second seed; its evaluations.
# The 10-demo models train half the steps (steps in proportion to the data, as in v1).
# What ran on 2026-11-22 (part 1, stopped after 30 minutes on the machine): the first version of this
# script trained the 25-demo and 10-demo models at once, the 25-demo one ran out of GPU memory, and the
# rest ran in this order; the 25-demo training had reached step 1,060 when it was stopped (part 2 did
# not run).
#
# On a one-GPU workstation with rvt2 and its simulator installed:
# `bash scripts/offline-gpu-host/gpu_results_v2_1gpu.sh all1` (then all2). On a GPU machine without
# network access, one command per step, back to back (its /tmp lives while the machine stays up): `stash`
# carrying each .gpu/site.part.* piece but the last (pack_gpu_wheels.sh), then `start1` (or `start2`)
# carrying the last piece and .gl, then `collect1` (`collect2`) until it reports everything (each waits
# up to 9 minutes).
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
export WORKERS=${WORKERS:-14}
self=scripts/offline-gpu-host/$(basename "$0")
onebox=scripts/offline-gpu-host/gpu_onebox.sh
COMPILE=${COMPILE---compile}          # a dry run on a CPU: COMPILE= STEPS_25=8 STEPS_10=4 (and gpu_onebox.sh's settings)
STEPS_25=${STEPS_25:-1100}
STEPS_10=${STEPS_10:-550}

next() {  # next RUN ARGS STEPS [EVAL_RUN EVAL_EPISODES]: train RUN in the background while EVAL_RUN is evaluated
  RUN=$1 TRAIN_ARGS=$2 STEPS=$3 START_WAIT=1 bash $onebox bg "$1" train
  if [ -n "${4:-}" ]; then RUN=$4 EVAL_EPISODES=$5 WORKERS=10 bash $onebox eval offline; fi  # 10 simulator processes: the training keeps its cores
  WAIT_S=100000 bash $onebox wait "$1"
}

case ${1:-} in
  stash) bash $onebox stash ;;
  start1|start2)
    bash $onebox stash setup
    bash $onebox bg chain "$self" "chain${1#start}" ;;  # in the background: a command ends after 10 minutes
  chain1)
    bash $onebox record heldout loopbench
    next demos10 "$COMPILE --episodes-per-task 10" "$STEPS_10"
    next front10 "$COMPILE --episodes-per-task 10 --cameras front" "$STEPS_10" demos10 50
    next seed0 "$COMPILE --seed 0" "$STEPS_25" front10 25
    RUN=seed0 bash $onebox eval repro offline ;;
  chain2)
    bash $onebox record heldout
    next seed1 "$COMPILE --seed 1" "$STEPS_25"
    RUN=seed1 bash $onebox eval offline ;;
  collect1|collect2)
    runs="seed0 demos10 front10"
    [ "$1" = collect2 ] && runs="seed1"
    WAIT_S=${WAIT_S:-540} bash $onebox wait chain || true
    RUNS=$runs bash $onebox results ;;
  all1|all2)
    n=${1#all}
    bash $onebox setup && bash "$self" "chain$n" && bash "$self" "collect$n" ;;
  *) echo "usage: $0 stash|start1|collect1|start2|collect2|all1|all2" >&2; exit 2 ;;
esac
