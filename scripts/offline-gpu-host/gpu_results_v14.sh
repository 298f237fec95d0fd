#!/usr/bin/env bash
# Results v14 (docs/RESULTS.md): each keyframe predicted from several views of the scene, their medoid kept
# (`rvt2 eval --consensus K`), which rvt2 does not keep: apply
# benchmarks/results/v14_h100/consensus/consensus.patch to a checkout of 520996d first (the views' modes
# refuse to run without it). Two trained models, unchanged. First the 10-demo model of results v12 (run
# v12_10) on seeds no policy is scored on, 30 per task from 20000, all 8 tasks, with one view and with K
# (reports sel_10_k1, sel_10_k$K): the rule, fixed before the runs, is that K views are kept if they do
# not lose episodes there. Then both models on the evaluation seeds, 50 per task from 10000, with K views
# (eval_v14_10, then the 25-demo model of results v11, run v11: eval_v14). Their one-view evaluations on
# the same machine kind and seeds are results v13's (eval_v13_10, eval_v13).
#
# The weights: each run's float16 pieces (gpu_checkpoint.py shrink; 10 pieces and meta.tar, about 150 MiB)
# restored by `gpu_onebox.sh restore`.
# `replicate` trains the 10-demo recipe of results v11/v12 once more, only the training seed changed (1; v12_10
# trained with 0), and evaluates it as v12_10 was (gpu_results_v11.sh with RUN=v14_10_seed1; on one GPU
# machine: `stash` x3 carrying .gpu/site.part.aa .. .ac, `replicate start` carrying .gpu/site.part.ad,
# .gpu/site.sha256 and .gl, then `replicate collect` until the log says the chain is done: 29 minutes on
# one H100 with 16 cores).
# On a workstation with rvt2 and its simulator installed and both runs in $W/runs/:
#   bash scripts/offline-gpu-host/gpu_results_v14.sh all
# (a dry run on a CPU: SEL_EPISODES=1 EVAL_EPISODES=1 EXTRA="--tasks push_cube" DEVICE=cpu WORKERS=1 ... all)
# On a GPU machine without network access (64 MiB carried per command), as run: `stash` once per carry,
# carrying .gpu/site.part.aa, .ab, .ac, then v12_10's pieces in .gpu/tendemo_a/ .. _c/ (parts 000-002 with
# meta.tar's config.json, manifest.json and instructions.safetensors, 003-005, 006-008), then v11's the same
# way in .gpu/weights_a/ .. _c/; then `evaluate`, carrying .gpu/site.part.ad, .gpu/site.sha256, .gl,
# .gpu/tendemo_d/ and .gpu/weights_d/ (009), its output sent to a file (a pipe waits for the background
# job); then `collect` until the log says both evaluations are done. As run, the evaluation on seeds
# 10000+ was stopped once seeds 20000+ had rejected the views.
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
onebox=scripts/offline-gpu-host/gpu_onebox.sh
self=scripts/offline-gpu-host/$(basename "$0")
export W=${W:-/tmp/w} WORKERS=${WORKERS:-14}
TEN=${TEN:-v12_10} TWENTYFIVE=${TWENTYFIVE:-v11} CONSENSUS=${CONSENSUS:-5}
RUNS="sel_10_k1 sel_10_k$CONSENSUS v14_10 v14"

case ${1:-} in
  stash)
    PIECES=.gpu/tendemo WEIGHTS=$W/weights_$TEN bash $onebox stash
    PIECES=.gpu/weights WEIGHTS=$W/weights_$TWENTYFIVE bash $onebox stash ;;
  evaluate|evalchain|all)
    grep -q "consensus" rvt2cli/eval/options.py || {
      echo "rvt2 eval has no --consensus here: git apply benchmarks/results/v14_h100/consensus/consensus.patch first" >&2; exit 2; } ;;&
  evaluate)  # unpack, restore the runs whose pieces are here, evaluate in the background
    bash "$self" stash
    bash $onebox setup
    for run in "$TEN" "$TWENTYFIVE"; do
      if [ -f "$W/weights_$run/weights.part009" ]; then RUN=$run WEIGHTS=$W/weights_$run bash $onebox restore; fi
    done
    bash $onebox bg eval "$self" evalchain ;;
  evalchain)
    heldout="--seed 20000 --episodes ${SEL_EPISODES:-30}"
    for views in 1 "$CONSENSUS"; do
      RUN=$TEN EVAL_NAME=sel_10_k$views EVAL_ARGS="$heldout --consensus $views ${EXTRA:-}" bash $onebox eval || echo "evaluating $TEN failed"
    done
    for pair in "$TEN v14_10" "$TWENTYFIVE v14"; do
      set -- $pair
      if [ -d "$W/runs/$1" ]; then
        RUN=$1 EVAL_NAME=$2 EVAL_ARGS="--consensus $CONSENSUS ${EXTRA:-}" bash $onebox eval || echo "evaluating $1 failed"
      fi
    done ;;
  collect)
    WAIT_S=${WAIT_S:-540} bash $onebox wait ${WAIT_FOR:-eval} || true
    RUNS=$RUNS bash $onebox results ;;
  replicate)
    EPISODES=10 RUN=${REPLICATE:-v14_10_seed1} CHAIN=through \
      TRAIN="--rotation-bins 360 --rotation-sigma 2 --start-share 0.5 --aim-held --coarse-action-features --task-weights insert_peg=3,plug_charger=3 --seed 1" \
      bash scripts/offline-gpu-host/gpu_results_v11.sh "${2:-all}" ;;
  all)
    bash $onebox setup && bash "$self" evalchain
    RUNS=$RUNS bash $onebox results ;;
  *) echo "usage: $0 stash|evaluate|evalchain|collect|replicate [start|collect|all]|all" >&2; exit 2 ;;
esac
