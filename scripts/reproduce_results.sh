#!/usr/bin/env bash
# docs/RESULTS.md (v2) on a GPU workstation with rvt2 and its simulator installed (`make setup`), on
# GPUS GPUs: record 8 tasks x 25 demos and 5 held-out demos per task (seeds 30000+), extract keyframes,
# train the paper configuration (torchrun when GPUS > 1; the global batch BATCH is kept by dividing it
# among the GPUs), evaluate closed-loop on seeds 10000-10049 and score the held-out demos offline. Every
# phase is timed into $DATA/phases.tsv.
#
#   bash scripts/reproduce_results.sh                      # every phase, one GPU
#   GPUS=2 bash scripts/reproduce_results.sh               # training on two GPUs (batch 96 each)
#   bash scripts/reproduce_results.sh train eval offline   # some phases, in this order
#   RUN=demos10 STEPS=550 TRAIN_ARGS="--compile --episodes-per-task 10" bash scripts/reproduce_results.sh train eval offline
#
# Measured on one NVIDIA H200 (16 CPU cores, 14 simulator processes): record 265 s and keyframes 35 s,
# held-out demos 223 s; the training's compiled loop runs at 723 samples/s at batch 192
# (docs/BENCHMARKS.md, "Training loop"); two H200s train 1.94x as fast as one ("Several GPUs").
# Settings (environment): GPUS, BATCH (global), STEPS, SEED, TRAIN_ARGS, RUN, WORKERS (simulator
# processes), EPISODES (demos per task), EVAL_EPISODES, HELDOUT_EPISODES, TASKS, DEVICE (for eval),
# DATA (the output folder, default data/results; data/ is git-ignored), RVT2 (the command).
set -euo pipefail
GPUS=${GPUS:-1}
BATCH=${BATCH:-192}
STEPS=${STEPS:-1100}
SEED=${SEED:-0}
TRAIN_ARGS=${TRAIN_ARGS:---compile}
RUN=${RUN:-demos25_seed$SEED}
WORKERS=${WORKERS:-$(( $(nproc) > 3 ? $(nproc) - 2 : 1 ))}   # leave two cores to the GPU's feeder
EPISODES=${EPISODES:-25}
EVAL_EPISODES=${EVAL_EPISODES:-50}
HELDOUT_EPISODES=${HELDOUT_EPISODES:-5}
TASKS=${TASKS:-"insert_peg plug_charger place_sphere lift_peg_upright stack_cube pick_cube push_cube pull_cube"}
DATA=${DATA:-data/results}
DEVICE=${DEVICE:-cuda}
RVT2=${RVT2:-rvt2}
if (( GPUS < 1 || BATCH % GPUS != 0 )); then
  echo "GPUS=$GPUS: give a number of GPUs that divides the global batch BATCH=$BATCH" >&2
  exit 2
fi
if ! command -v "$RVT2" > /dev/null; then
  echo "$RVT2: not found; run \`make setup\` and \`source .venv/bin/activate\` (or set RVT2)" >&2
  exit 2
fi
[ $# -gt 0 ] || set -- record heldout train eval offline
for step in "$@"; do
  case $step in record|heldout|train|eval|offline) ;; *) echo "usage: $0 [record|heldout|train|eval|offline]..." >&2; exit 2 ;; esac
done
mkdir -p "$DATA"

phase() {  # NAME COMMAND...: run COMMAND, then append "NAME<TAB>seconds" to $DATA/phases.tsv
  local name=$1 start=$SECONDS
  shift
  echo "== $name"
  "$@"
  printf '%s\t%d\n' "$name" $((SECONDS - start)) | tee -a "$DATA/phases.tsv"
}

record() {  # OUT FIRST_SEED EPISODES
  for task in $TASKS; do
    $RVT2 record --task "$task" --episodes "$3" --seed "$2" --workers "$WORKERS" --out "$1" --no-progress
  done
  $RVT2 extract-keyframes "$1"
}

train() {
  local launch=($RVT2)
  if (( GPUS > 1 )); then launch=(torchrun --standalone --nproc-per-node "$GPUS" -m rvt2cli); fi
  # shellcheck disable=SC2086  # TRAIN_ARGS is a list of options
  "${launch[@]}" train --data "$DATA/demos" --out "$DATA/runs/$RUN" --config rvt2 --seed "$SEED" \
    --batch-size $((BATCH / GPUS)) --steps "$STEPS" --warmup $((STEPS / 10)) --val-episodes 1 \
    --val-every $((STEPS / 4)) --save-every $((STEPS / 4)) --no-progress $TRAIN_ARGS
}

evaluate() {
  $RVT2 eval --checkpoint "$DATA/runs/$RUN" --episodes "$EVAL_EPISODES" --seed 10000 --workers "$WORKERS" \
    --device "$DEVICE" --out "$DATA/evals/$RUN" --no-progress
}

offline() {
  $RVT2 eval --checkpoint "$DATA/runs/$RUN" --offline "$DATA/heldout" --device "$DEVICE" --out "$DATA/offline/$RUN" --no-progress
}

for step in "$@"; do
  case $step in
    record) phase record record "$DATA/demos" 0 "$EPISODES" ;;
    heldout) phase heldout record "$DATA/heldout" 30000 "$HELDOUT_EPISODES" ;;
    train) phase "train_$RUN" train ;;
    eval) phase "eval_$RUN" evaluate ;;
    offline) phase "offline_$RUN" offline ;;
  esac
done
echo "reports: $DATA/evals/$RUN/eval.md, $DATA/offline/$RUN/offline.md; phase times: $DATA/phases.tsv"
