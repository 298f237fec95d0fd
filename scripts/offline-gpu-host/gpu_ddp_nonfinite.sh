#!/usr/bin/env bash
# Which part of training on several GPUs makes steps non-finite (docs/RESULTS.md v10): on a machine with
# two GPUs, v8's recipe trained for STEPS (300) steps on the same demos, once on one GPU (batch 192) and
# once per variant on two (batch 96 each): as rvt2 trains by default (bf16, --compile, 8-bit LAMB, the warp
# renderer), then with one of them changed: uncompiled, compiled without Dynamo splitting the graphs at
# DDP's gradient buckets (torch._dynamo.config.optimize_ddp = False, set by a sitecustomize.py),
# --no-amp (float32), --no-8bit (32-bit LAMB states), --render-backend torch. Each run's steps, skipped steps and samples/s go to ddp_nonfinite.tsv;
# the variant that skips none where the default skips points at the fault. The warmup is a tenth of STEPS,
# so the learning rate passes the 1e-3 where v2's and v10's two-GPU runs began to skip within 300 steps.
#
# On a workstation with two GPUs and rvt2 installed: `bash scripts/offline-gpu-host/gpu_ddp_nonfinite.sh all`.
# On a GPU machine without network access: `stash` (x3), `start`, then `collect` until the log says the
# chain is done (about 15 minutes on 2 x H200 with TASKS of three tasks, 25 demos each; an estimate).
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
onebox=scripts/offline-gpu-host/gpu_onebox.sh
self=scripts/offline-gpu-host/$(basename "$0")
export TASKS=${TASKS:-"insert_peg plug_charger pick_cube"} WORKERS=${WORKERS:-14} STEPS=${STEPS:-300}
RECIPE=${RECIPE:---rotation-bins 360 --rotation-sigma 2 --start-share 0.5 --aim-held --coarse-action-features}
COMPILE=${COMPILE---compile}          # a dry run on a CPU: COMPILE= STEPS=20 BATCH=4 CONFIG=small
W=${W:-/tmp/w}
# variant name, processes, options beyond the recipe (the first two are the control and the fault)
VARIANTS=(
  "one_gpu 1 $COMPILE"
  "two_gpus 2 $COMPILE"
  "two_gpus_uncompiled 2"
  "two_gpus_unsplit 2 $COMPILE"
  "two_gpus_float32 2 $COMPILE --no-amp"
  "two_gpus_lamb32 2 $COMPILE --no-8bit"
  "two_gpus_torch_render 2 $COMPILE --render-backend torch"
)
runs() { for v in "${VARIANTS[@]}"; do echo "nf_${v%% *}"; done; }

case ${1:-} in
  stash) bash $onebox stash ;;
  start) bash $onebox stash setup bg chain "$self" chain ;;  # the chain in the background: a command ends after 10 minutes
  chain)
    bash $onebox record merged
    printf 'variant\tprocesses\toptions\tsteps\tskipped\tsamples_per_s\n' > "$W/ddp_nonfinite.tsv"
    mkdir -p "$W/unsplit" && printf '%s\n' 'import sys' 'import torch._dynamo' \
      'torch._dynamo.config.optimize_ddp = False' 'print("sitecustomize: optimize_ddp off", file=sys.stderr)' \
      > "$W/unsplit/sitecustomize.py"
    for v in "${VARIANTS[@]}"; do
      read -r name processes options <<< "$v"
      extra=; [ "$name" = two_gpus_unsplit ] && extra=$W/unsplit
      EXTRA_PYTHONPATH=$extra RUN=nf_$name NPROC=$processes DATA=$W/demos_merged TRAIN_ARGS="$RECIPE ${options:-}" \
        bash $onebox train \
        || echo "nf_$name stopped (its skipped steps are in its train.csv)"
      last=$(tail -1 "$W/runs/nf_$name/train.csv" 2>/dev/null | tr -d '\r' || true)
      IFS=, read -r step _ _ _ _ _ _ _ _ _ _ rate skipped <<< "${last:-none}" || true
      printf '%s\t%s\t%s\t%s\t%s\t%.0f\n' "$name" "$processes" "${options:-none}" "${step:-none}" "${skipped:-none}" "${rate:-0}" \
        | tee -a "$W/ddp_nonfinite.tsv"
    done ;;
  collect)
    WAIT_S=${WAIT_S:-540} bash $onebox wait chain || true
    cp "$W/ddp_nonfinite.tsv" "${OUT:-/tmp/rvt2-out}/" 2>/dev/null || true
    RUNS="$(runs | tr '\n' ' ')" bash $onebox results ;;
  all)
    bash $onebox setup && bash "$self" chain
    cp "$W/ddp_nonfinite.tsv" "${OUT:-/tmp/rvt2-out}/"
    RUNS="$(runs | tr '\n' ' ')" bash $onebox results ;;
  *) echo "usage: $0 stash|start|collect|all" >&2; exit 2 ;;
esac
