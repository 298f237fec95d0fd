#!/usr/bin/env bash
# A model's whole run, chosen on validation seeds and then reported: record and train an experiment file, evaluate
# its last checkpoint on validation seeds and earlier checkpoints on their first seeds (the success-vs-training
# curve), then the file's reported evaluations one after another (each its own command: a run cut short keeps
# those finished). The reported evaluations are fixed before the validation results exist: this repeats a model
# already chosen, and the validation seeds say whether it would have been.
#
#   bash scripts/choose_then_report.sh experiments/rvt2_18_via.toml --gpus 4 --workers 60   # a GPU workstation
#   KIT=1 NPROC=4 WORKERS=60 bash scripts/offline-gpu-host/gpu_onebox.sh stash setup bg main \
#     scripts/choose_then_report.sh experiments/rvt2_18_via.toml                             # the offline kit
#
# Settings (environment): VALIDATION (seeds, default 20000-20049), CURVE_STEPS (default 1500,3000,4500; none: no curve),
# CURVE_EPISODES (per task at the earlier checkpoints, default 25), REPORT (the file's evaluations in the order
# run, default "main paraphrases"), RENDERER (instead of the file's: demos and evaluations alike).
# Options after the file go to every `python -m benchmarks.experiment` (workstation only; the kit takes NPROC
# and WORKERS).
set -euo pipefail
cd "$(dirname "$0")/.."
file=${1:?give an experiment file, e.g. experiments/rvt2_18_via.toml}
shift
renderer=${RENDERER:+--renderer $RENDERER}

phase() {  # PHASES OPTIONS...: one `benchmarks.experiment` command
  local phases=$1
  shift
  if [ -n "${KIT:-}" ]; then
    EXPERIMENT_ARGS="$renderer $*" bash scripts/offline-gpu-host/gpu_onebox.sh experiment "$file" "$phases"
  else
    bash scripts/reproduce_results.sh "$file" --phase "$phases" $renderer "$@"
  fi
}

phase record,train "$@"
curve=(--eval-steps "${CURVE_STEPS:-1500,3000,4500}" --curve-episodes "${CURVE_EPISODES:-25}")
if [ "${CURVE_STEPS:-}" = none ]; then curve=(); fi   # the last checkpoint alone (a machine short of time)
phase eval --eval-seeds "${VALIDATION:-20000-20049}" "${curve[@]}" "$@"
for evaluation in ${REPORT:-main paraphrases}; do
  phase eval --evaluations "$evaluation" "$@"
done
