#!/usr/bin/env bash
# Results v11 (docs/RESULTS.md): v10's 8-task model trained on one GPU, long enough for the insertions.
# v8's recipe (8 tasks x 25 demos, refinements merged, batch 192, --rotation-bins 360 --rotation-sigma 2
# --start-share 0.5 --aim-held --coarse-action-features) with the two insertions drawn three times as often
# as each other task (--task-weights insert_peg=3,plug_charger=3), 3,200 steps on one GPU: each insertion
# gets 800 of v8's steps' worth of samples (v8: 150; v9's one-task models: 1,200), each other task 267.
# 2 x 10 held-out insertion demos are recorded while it trains and score it offline; then it is evaluated
# closed loop with the insertion search on 50 seeds per task, the two insertions first (eval_${RUN}_ins,
# then eval_${RUN}_rest).
#
# On a workstation with rvt2 and its simulator installed: `bash scripts/offline-gpu-host/gpu_results_v11.sh all`
# (`EPISODES=10 RUN=v11_10` for the 10-demo model).
# On a GPU machine without network access (commands of at most 10 minutes): `stash` (x3), `CHAIN=through start`, then
# `collect` until the log says the chain is done (26-27 minutes in all on one H200 with 16 cores). As run, the
# 25-demo model's chain was `start` (record, train, score offline), then `weights 0 4`, `weights 4 4` and
# `weights 8 4` carried its weights off (float16 pieces; `tar -xf meta.tar` among them, then
# gpu_checkpoint.py restore), `bash scripts/offline-gpu-host/gpu_onebox.sh bg eval <this script> evalchain` and
# `collect-eval` evaluated it; the 10-demo model ran on a second machine with `EPISODES=10 RUN=v11_10
# CHAIN=through start` and `collect`. `evaluate` evaluates weights trained elsewhere: their pieces carried in
# as .gpu/weights*/ beside the site pieces, `stash` (x3), `evaluate`, `collect-eval`.
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
onebox=scripts/offline-gpu-host/gpu_onebox.sh
self=scripts/offline-gpu-host/$(basename "$0")
export NPROC=${NPROC:-1} WORKERS=${WORKERS:-14} STEPS=${STEPS:-3200} RUN=${RUN:-v11}
COMPILE=${COMPILE---compile}          # a dry run on a CPU: COMPILE= STEPS=8 EVAL_EPISODES=1 (and gpu_onebox.sh's settings)
TRAIN=${TRAIN:---rotation-bins 360 --rotation-sigma 2 --start-share 0.5 --aim-held --coarse-action-features --task-weights insert_peg=3,plug_charger=3}
INSERTIONS=${INSERTIONS:-insert_peg,plug_charger}
OTHERS=${OTHERS:-place_sphere,lift_peg_upright,stack_cube,pick_cube,push_cube,pull_cube}
W=${W:-/tmp/w}
RUNS="$RUN ${RUN}_ins ${RUN}_rest"

case ${1:-} in
  stash) bash $onebox stash ;;
  start) bash $onebox stash setup bg chain "$self" ${CHAIN:-chain} ;;  # in the background: a command ends after 10 minutes
  chain)  # machine 1: record, train, score offline
    bash $onebox record merged
    # the held-out demos record on a few cores while the model trains on the GPU
    HELDOUT_TASKS=${HELDOUT_TASKS:-"insert_peg plug_charger"} HELDOUT_EPISODES=${HELDOUT_EPISODES:-10} WORKERS=8 \
      MERGE_DIRS=heldout bash $onebox heldout merged > "$W/heldout.out" 2>&1 &
    heldout=$!
    DATA=$W/demos_merged TRAIN_ARGS="$COMPILE $TRAIN" bash $onebox train || { wait "$heldout"; exit 1; }
    wait "$heldout" || echo "recording the held-out demos failed: $W/heldout.out"
    OFFLINE_DEMOS=$W/heldout_merged bash $onebox offline || echo "scoring $RUN offline failed" ;;
  collect)
    WAIT_S=${WAIT_S:-540} bash $onebox wait chain || true
    RUNS=$RUNS bash $onebox results ;;
  weights) bash $onebox weights "${2:?weights FIRST COUNT}" "${3:?weights FIRST COUNT}" ;;
  evaluate) bash $onebox stash setup restore bg eval "$self" evalchain ;;  # machine 2: the weights carried in
  evalchain)
    EVAL_NAME=${RUN}_ins EVAL_ARGS="--tasks $INSERTIONS" bash $onebox eval || echo "evaluating $RUN on $INSERTIONS failed"
    EVAL_NAME=${RUN}_rest EVAL_ARGS="--tasks $OTHERS" bash $onebox eval || echo "evaluating $RUN on $OTHERS failed" ;;
  collect-eval)
    WAIT_S=${WAIT_S:-540} bash $onebox wait eval || true
    RUNS=$RUNS bash $onebox results ;;
  through) bash "$self" chain && bash "$self" evalchain ;;  # one machine: CHAIN=through for `start`
  all) bash $onebox setup && bash "$self" chain && bash "$self" evalchain && RUNS=$RUNS bash $onebox results ;;
  *) echo "usage: $0 stash|start|chain|collect|weights FIRST COUNT|evaluate|evalchain|collect-eval|through|all" >&2; exit 2 ;;
esac
