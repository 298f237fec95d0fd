#!/usr/bin/env bash
# Train the v1 models of docs/RESULTS.md on a GPU machine without network access, which has CUDA torch
# but no simulator and no MCAP libraries, and takes at most 64 MiB in and gives 64 MiB back per transfer.
#
# Online:  rvt2 pack-samples DEMOS --keyframe-starts-only --out samples.safetensors
#          xz --delta=dist=2 --lzma2=preset=6 -T2 -c samples.safetensors | split -b 50m - .gpu/samples.xz.part.
#          (cd .gpu && sha256sum samples.xz.part.* > samples.sha256)      # .gpu/ is git-ignored
# Offline host, one command per step, each carrying .gpu/ with the pieces not yet sent; K=scripts/offline-gpu-host:
#   bash $K/gpu_train.sh stash                  # keep the pieces in /tmp/w (kept while the machine stays up)
#   bash $K/gpu_train.sh start                  # check + unpack the samples, train in the background
#   bash $K/gpu_train.sh fetch RUN FIRST COUNT  # wait for RUN, copy weight pieces FIRST.. (4 per transfer) to $OUT
# Online:  python $K/gpu_checkpoint.py restore PIECES_DIR runs/RUN
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
KIT=scripts/offline-gpu-host
W=${W:-/tmp/w}
STEPS25=${STEPS25:-8000}
STEPS10=${STEPS10:-4000}
STEPS_LONG=${STEPS_LONG:-16000}
CONFIG=${CONFIG:-rvt2}
RUNS=${RUNS:-"demos25 demos10"}   # demos25_16k: the 25-demo model trained twice as long
phase=$1
shift

train_run() {  # NAME ARGS...: one run, then its checkpoint cut into pieces for fetching
  local name=$1
  shift
  local common=(--data "$W/samples.safetensors" --config "$CONFIG" --render-backend torch --val-episodes 0 --save-every 2500 --no-progress)
  echo "=== $name start $(date -u +%FT%TZ)"
  if ! python3 -m rvt2cli train "${common[@]}" --out "$W/runs/$name" --compile "$@"; then
    echo "=== $name: the compiled run failed; again without --compile"
    rm -rf "$W/runs/$name"
    python3 -m rvt2cli train "${common[@]}" --out "$W/runs/$name" "$@"
  fi
  echo "=== $name end $(date -u +%FT%TZ)"
  python3 $KIT/gpu_checkpoint.py shrink "$W/runs/$name" "$W/export/$name"
  cp "$W/runs/$name/train.csv" "$W/runs/$name/run.json" "$W/export/$name/"
  touch "$W/export/$name/DONE"
}

case $phase in
stash)
  mkdir -p $W && cp .gpu/* $W/ && ls -l $W
  ;;
start)
  mkdir -p $W && cp .gpu/* $W/
  (cd $W && sha256sum -c samples.sha256)
  cat $W/samples.xz.part.* | xz -d > $W/samples.safetensors
  rm -rf $W/src && mkdir -p $W/src && cp -r rvt2cli scripts $W/src/   # later commands replace the working tree
  cd $W/src
  RUNS="$RUNS" setsid nohup bash $KIT/gpu_train.sh background > $W/train.log 2>&1 < /dev/null &
  sleep "${START_WAIT:-90}"
  cat $W/train.log
  ;;
background)
  export PYTHONPATH=$W/src PYTHONUNBUFFERED=1
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
  python3 -c "import torch; print('torch', torch.__version__)"
  for run in $RUNS; do
    case $run in
      demos25) train_run demos25 --steps "$STEPS25" ;;
      demos10) train_run demos10 --steps "$STEPS10" --episodes-per-task 10 ;;
      demos25_16k) train_run demos25_16k --steps "$STEPS_LONG" ;;
    esac
  done
  echo "=== all done $(date -u +%FT%TZ)"
  ;;
fetch)
  name=$1 first=$2 count=$3 wait_s=${4:-540}
  while [ ! -f "$W/export/$name/DONE" ] && [ "$SECONDS" -lt "$wait_s" ]; do sleep 5; done
  grep -a "===\|trained\|data:\|model:\|Error\|error" $W/train.log | tail -20 || true
  for csv in $W/runs/*/train.csv; do echo "$csv: $(tail -1 "$csv")"; done
  if [ -f "$W/export/$name/DONE" ]; then
    mkdir -p "$OUT/$name"
    for i in $(seq "$first" $((first + count - 1))); do
      piece=$(printf "%s/export/%s/weights.part%03d" $W "$name" "$i")
      [ -f "$piece" ] && cp "$piece" "$OUT/$name/"
    done
    if [ "$first" = 0 ]; then
      cp $W/export/"$name"/{config.json,instructions.safetensors,manifest.json,train.csv,run.json} "$OUT/$name/"
      cp $W/train.log "$OUT/$name/"
    fi
    ls -l "$OUT/$name"
  else
    echo "$name: not finished yet"
  fi
  ;;
*)
  echo "usage: $0 stash|start|background|fetch RUN FIRST COUNT [WAIT_S]" >&2
  exit 2
  ;;
esac
