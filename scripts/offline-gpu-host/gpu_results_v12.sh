#!/usr/bin/env bash
# Results v12 (docs/RESULTS.md): v11's 8-task model, unchanged, evaluated again with today's executor, whose
# insertion search probes plug_charger on a wider grid (tasks/plug_charger.toml: a 1 mm pitch and a 1.5 mm
# retract, so 40 probes reach 3.6 mm across the receptacle's axis within the episode's control steps;
# v11: 0.5 mm and 4 mm, 1.8 mm). 50 seeds per task from 10000, the two insertions first
# (eval_${NAME}_ins, then eval_${NAME}_rest: their executor is unchanged, so they check that the weights came
# back as they were trained).
#
# The weights: v11's run folder, or its float16 pieces (gpu_checkpoint.py shrink; 10 pieces and meta.tar,
# 143 MiB) restored by `gpu_onebox.sh restore`.
# On a workstation with rvt2 and its simulator installed and the run in $W/runs/$RUN:
#   bash scripts/offline-gpu-host/gpu_results_v12.sh all
# On a GPU machine without network access (64 MiB carried per command), as run: `stash` six times, carrying
# .gpu/site.part.aa, .ab, .ac, then the weight pieces in three folders .gpu/weights_a/ (parts 000-002, with
# meta.tar's config.json, manifest.json and instructions.safetensors), .gpu/weights_b/ (003-005),
# .gpu/weights_c/ (006-008); then `evaluate`, carrying .gpu/site.part.ad,
# .gpu/site.sha256, .gl and .gpu/weights_d/ (009); then `collect` until the log says the evaluation is done
# (about 5 minutes on one H200 with 16 cores).
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
onebox=scripts/offline-gpu-host/gpu_onebox.sh
self=scripts/offline-gpu-host/$(basename "$0")
export RUN=${RUN:-v11} WORKERS=${WORKERS:-14}
NAME=${NAME:-v12}
INSERTIONS=${INSERTIONS:-insert_peg,plug_charger}
OTHERS=${OTHERS:-place_sphere,lift_peg_upright,stack_cube,pick_cube,push_cube,pull_cube}
RUNS="${NAME}_ins ${NAME}_rest"

case ${1:-} in
  stash) bash $onebox stash ;;
  evaluate) bash $onebox stash setup restore bg eval "$self" evalchain ;;  # in the background
  evalchain)
    EVAL_NAME=${NAME}_ins EVAL_ARGS="--tasks $INSERTIONS" bash $onebox eval || echo "evaluating $RUN on $INSERTIONS failed"
    EVAL_NAME=${NAME}_rest EVAL_ARGS="--tasks $OTHERS" bash $onebox eval || echo "evaluating $RUN on $OTHERS failed" ;;
  collect)
    WAIT_S=${WAIT_S:-540} bash $onebox wait eval || true
    RUNS=$RUNS bash $onebox results ;;
  all) bash $onebox setup && bash "$self" evalchain && RUNS=$RUNS bash $onebox results ;;
  *) echo "usage: $0 stash|evaluate|evalchain|collect|all" >&2; exit 2 ;;
esac
