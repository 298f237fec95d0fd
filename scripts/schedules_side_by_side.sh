#!/usr/bin/env bash
# Training schedules of one experiment file compared on validation seeds, one GPU each, on one recording: record
# the file's demos once, then train every schedule (a number of steps, warmup and cosine decay as the file sets
# them) from those demos, each on a GPU of its own, at the same time, and evaluate each last checkpoint on the
# validation seeds. Each schedule's training runs as on a one-GPU host; they share the host's cores (each
# evaluation gets its share of the workers). With fewer GPUs than schedules, those that share a GPU run one after
# another (no GPU: all one after another).
#
#   bash scripts/schedules_side_by_side.sh experiments/rvt2_18_onegpu_via.toml 3500,4000       # a GPU workstation
#   KIT=1 WORKERS=30 bash scripts/offline-gpu-host/gpu_onebox.sh stash setup bg main \
#     scripts/schedules_side_by_side.sh experiments/rvt2_18_onegpu_via.toml 3500,4000           # the offline kit
#
# Folders: the recording in NAME/ (in ROOT, default data/experiments/, on a workstation; the kit's /tmp/w), each schedule in
# NAME_STEPSsteps/ (its demos a link to NAME/demos), the reports in NAME_STEPSsteps/evals/seed0_from20000.
# Settings (environment): VALIDATION (seeds, default 20000-20049), WORKERS (simulator processes in all, default
# the cores less two), RENDERER (instead of the file's: demos and evaluations alike). Options after the steps go to
# every `python -m benchmarks.experiment` (workstation only). The choice among the schedules is made on these
# seeds; the reported seeds wait for it.
set -euo pipefail
usage="usage: $0 EXPERIMENT_FILE STEPS,STEPS,... (e.g. experiments/rvt2_18_onegpu_via.toml 3500,4000)"
file=${1:?$usage}
schedules=${2:?$usage}
[ -f "$file" ] || { echo "$file: no such experiment file; $usage" >&2; exit 2; }
file=$(realpath "$file")   # named from here, read from the repository root
if [ -n "${ROOT:-}" ]; then ROOT=$(realpath -m "$ROOT"); fi
cd "$(dirname "$0")/.."
[[ $schedules =~ ^[0-9]+(,[0-9]+)*$ ]] || { echo "steps '$schedules': give numbers of steps, comma-separated; $usage" >&2; exit 2; }
shift 2
extra=("$@")   # options for every `benchmarks.experiment` command (a workstation; e.g. --device cpu)
IFS=, read -r -a steps <<< "$schedules"
name=$(basename "$file" .toml)
workers=${WORKERS:-$(( $(nproc) > 3 ? $(nproc) - 2 : 1 ))}
renderer=${RENDERER:+--renderer $RENDERER}

if [ -n "${KIT:-}" ]; then root=${W:-/tmp/w}; else root=${ROOT:-data/experiments}; fi
# the GPUs this process may use, as CUDA_VISIBLE_DEVICES names them (rvt2cli.runtime.visible_gpus, as rvt2's workers
# see them); none: one slot, "", the schedules one after another
if [ -n "${KIT:-}" ]; then python=python3; else python=${PYTHON:-$(command -v python || echo .venv/bin/python)}; fi
listed=$("$python" -c 'from rvt2cli.runtime import visible_gpus; print("\n".join(visible_gpus()))')
mapfile -t gpus <<< "$listed"
slots=$(( ${#steps[@]} < ${#gpus[@]} ? ${#steps[@]} : ${#gpus[@]} ))
share=$(( workers / slots > 0 ? workers / slots : 1 ))

experiment() {  # FOLDER PHASES WORKERS OPTIONS...: one `benchmarks.experiment` command into ROOT/FOLDER
  local folder=$1 phases=$2 n=$3
  shift 3
  if [ -n "${KIT:-}" ]; then
    EXPERIMENT_FOLDER=$folder WORKERS=$n EXPERIMENT_ARGS="$renderer $*" \
      bash scripts/offline-gpu-host/gpu_onebox.sh experiment "$file" "$phases"
  else
    # shellcheck disable=SC2086  # $renderer is an option and its value
    bash scripts/reproduce_results.sh "$file" --phase "$phases" --out "$root/$folder" --workers "$n" $renderer "$@" ${extra[@]+"${extra[@]}"}
  fi
}

echo "$name: record once ($workers workers), then schedules ${steps[*]} on ${slots} GPU slot(s) [${gpus[*]}], $share workers each"
experiment "$name" record "$workers"

slot() {  # INDEX: the schedules this GPU slot trains and evaluates, one after another
  local index=$1 s
  for ((s = index; s < ${#steps[@]}; s += slots)); do
    local folder="${name}_${steps[s]}steps"
    mkdir -p "$root/$folder"
    ln -sfn "$(cd "$root/$name" && pwd)/demos" "$root/$folder/demos"
    CUDA_VISIBLE_DEVICES=${gpus[index]} experiment "$folder" train,eval "$share" \
      --steps "${steps[s]}" --eval-seeds "${VALIDATION:-20000-20049}" > "$root/$folder.log" 2>&1 \
      || { echo "$folder failed: $root/$folder.log" >&2; return 1; }
    echo "$folder done: $root/$folder/evals"
  done
}
pids=()
for ((i = 0; i < slots; i++)); do slot "$i" & pids+=($!); done
failed=0
for pid in "${pids[@]}"; do wait "$pid" || failed=1; done
exit $failed
