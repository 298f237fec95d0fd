#!/usr/bin/env bash
# Results v7 (docs/RESULTS.md) on one machine with one GPU (an NVIDIA H100 or H200 with 16 CPU cores):
# results v6's recipe (gpu_results_v6.sh: 8 tasks x 25 demos, refinements merged, batch 192, 1,200 steps,
# --rotation-bins 360 --rotation-sigma 2 --start-share 0.5, 50 seeds per task, 2 x 10 held-out insertion
# demos) on demos of an insert_peg expert variant that grasps the peg 6 cm behind its centre and stops the
# aligned TCP 195 mm before the box's face, whatever the peg's length. The variant made insert_peg worse
# and is not in rvt2: apply it first, and take it back after the recording
# (`git apply [-R] benchmarks/results/v7_h200/expert_fixed_offsets.patch`).
#
# On a one-GPU workstation with rvt2 and its simulator installed: `bash scripts/offline-gpu-host/gpu_results_v7.sh all`.
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
RUN=${RUN:-v7}
export HELDOUT_TASKS=${HELDOUT_TASKS:-"insert_peg plug_charger"} HELDOUT_EPISODES=${HELDOUT_EPISODES:-10}
W=${W:-/tmp/w}

variant_applied() {
  grep -q GRASP_BEHIND_CENTRE_M rvt2cli/record/experts.py ||
    { echo "$0: apply benchmarks/results/v7_h200/expert_fixed_offsets.patch first (the expert variant v7 measures)" >&2; exit 2; }
}

case ${1:-} in
  stash) bash $onebox stash ;;
  start)
    variant_applied
    bash $onebox stash setup
    bash $onebox bg chain "$self" chain ;;  # in the background: a command ends after 10 minutes
  chain)
    variant_applied
    bash $onebox record heldout merged
    RUN=$RUN DATA=$W/demos_merged TRAIN_ARGS="$COMPILE $TRAIN" bash $onebox train
    RUN=$RUN OFFLINE_DEMOS=$W/heldout_merged bash $onebox eval offline ;;
  collect)
    WAIT_S=${WAIT_S:-540} bash $onebox wait chain || true
    RUNS=$RUN bash $onebox results ;;
  all) variant_applied && bash $onebox setup && bash "$self" chain && RUNS=$RUN bash $onebox results ;;
  *) echo "usage: $0 stash|start|collect|all" >&2; exit 2 ;;
esac
