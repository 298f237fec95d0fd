#!/usr/bin/env bash
# The whole experiment on one GPU machine: record 8 tasks x 25 demos, train the paper configuration,
# evaluate 8 x 25 episodes closed-loop, with every phase timed. Written for this workplace's lent GPU
# machine (python3 3.12 with CUDA torch and numpy 2, no network, 64 MiB carried in per call, 10 min per
# command, /tmp kept while the machine stays warm); on your own GPU workstation run the two commands of
# README.md ("On a GPU workstation") instead.
#
# Here:    bash scripts/pack_gpu_wheels.sh            # -> .gpu/site.part.* (60 MiB each) + site.sha256
# There, one call per line, each carrying .gpu with the parts not sent yet:
#   bash scripts/gpu_onebox.sh stash                  # keep the carried parts in /tmp/w
#   bash scripts/gpu_onebox.sh setup bench record     # unpack, check the GPU renders, time the step, record
#   bash scripts/gpu_onebox.sh train                  # train in the background (BATCH, STEPS, LR below)
#   bash scripts/gpu_onebox.sh wait eval              # wait for training, then evaluate on the GPU
#   bash scripts/gpu_onebox.sh results                # phase times, logs, eval report -> $OUT/results.tgz
#   bash scripts/gpu_onebox.sh weights FIRST COUNT    # float16 weight pieces FIRST.. (and meta.tar with 0) to $OUT
# Here:    tar -xf meta.tar in the pieces' folder; python scripts/gpu_checkpoint.py restore PIECES_DIR runs/NAME
set -euo pipefail
W=${W:-/tmp/w}
SITE=${SITE:-/tmp/site}
WORKERS=${WORKERS:-14}
EPISODES=${EPISODES:-25}
TASKS=${TASKS:-"insert_peg plug_charger place_sphere lift_peg_upright stack_cube pick_cube push_cube pull_cube"}
RUN=${RUN:-onebox}
BATCH=${BATCH:-192}
STEPS=${STEPS:-4000}
CONFIG=${CONFIG:-rvt2}
DEVICE=${DEVICE:-cuda}
WAIT_S=${WAIT_S:-560}
OUT=${OUT:-/tmp/rvt2-out}
mkdir -p "$W" "$OUT"
export PYTHONPATH=$SITE:$PWD PYTHONUNBUFFERED=1 HF_HUB_OFFLINE=1 RVT2_EMBEDDINGS=$SITE/embeddings.safetensors
export LD_LIBRARY_PATH=${LD_LIBRARY_PATH:-}:/usr/local/nvidia/lib64:/usr/local/nvidia/lib
export RVT2_VULKAN=${RVT2_VULKAN:-nvidia}   # the point of this machine: say so at once if its GPU cannot render
RVT2=(python3 -m rvt2cli)
# run from this source tree: the package finds tasks/ and schemas/ where an install would put them
# (each call gets a fresh copy of the tree, so every call links them)
ln -sfn ../tasks rvt2cli/_tasks && ln -sfn ../schemas rvt2cli/_schemas
clock() { date +%s; }
phase() {  # NAME SECONDS: one line per phase in $W/phases.tsv
  printf '%s\t%.1f\n' "$1" "$2" | tee -a "$W/phases.tsv"
}

for step in "$@"; do
  case $step in
  stash)
    cp .gpu/site.part.* .gpu/site.sha256 "$W/" 2>/dev/null || true
    ls -l "$W"
    ;;
  setup)
    t=$(clock)
    if [ ! -f "$SITE/.unpacked" ]; then
      (cd "$W" && sha256sum -c site.sha256)
      mkdir -p "$SITE" && cat "$W"/site.part.* | xz -d | tar -x -C "$SITE" && touch "$SITE/.unpacked"
    fi
    if [ -d .gl ]; then  # Vulkan and GL loaders (apt-get download, carried): the image may have none
      for f in .gl/*.deb; do dpkg -x "$f" /; done
      ldconfig
    fi
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
    "${RVT2[@]}" doctor | tee -a "$OUT/gpu.txt"
    phase setup $(( $(clock) - t ))
    ;;
  bench)  # the training step rvt2 train runs, at the paper's batch and the one we train with
    t=$(clock)
    python3 -m benchmarks.policy_bench --configs rvt2 --batch "24,$BATCH" --compile --skip-inference --steps 15 \
      --json "$OUT/policy_bench.json" 2>&1 | tail -6
    phase bench $(( $(clock) - t ))
    ;;
  record)
    t=$(clock)
    for task in $TASKS; do
      "${RVT2[@]}" record --task "$task" --episodes "$EPISODES" --workers "$WORKERS" --out "$W/demos" --no-progress 2>&1 | tail -2
    done
    "${RVT2[@]}" extract-keyframes "$W/demos" | tail -1
    phase record $(( $(clock) - t ))
    ;;
  train)  # in the background: a later call waits for it
    rm -rf "$W/runs/$RUN" "$W/train.done"
    cat > "$W/train.sh" <<EOF
t=\$(date +%s)
${RVT2[*]} train --data $W/demos --out $W/runs/$RUN --config $CONFIG --batch-size $BATCH --steps $STEPS \
  --warmup $((STEPS / 10)) --val-episodes 1 --val-every $((STEPS / 4)) --save-every $((STEPS / 4)) --no-progress ${TRAIN_ARGS---compile}
echo "train \$? \$(( \$(date +%s) - t ))" > $W/train.done
EOF
    (cd "$PWD" && setsid nohup bash "$W/train.sh" > "$W/train.log" 2>&1 < /dev/null &)
    sleep "${START_WAIT:-60}"
    cat "$W/train.log"
    ;;
  wait)
    while [ ! -f "$W/train.done" ] && [ "$SECONDS" -lt "$WAIT_S" ]; do sleep 5; done
    tail -5 "$W/train.log"
    if [ ! -f "$W/train.done" ]; then echo "training still running"; exit 3; fi
    read -r _ rc seconds < "$W/train.done"
    phase train "$seconds"
    tail -2 "$W/runs/$RUN/train.csv"
    [ "$rc" = 0 ]
    ;;
  eval)
    t=$(clock)
    "${RVT2[@]}" eval --checkpoint "$W/runs/$RUN" --episodes "$EPISODES" --workers "$WORKERS" --device "$DEVICE" \
      --out "$W/eval_$RUN" --no-progress 2>&1 | tail -12
    phase eval $(( $(clock) - t ))
    ;;
  results)  # every small result in one file (a call returns at most 8 files)
    cp "$W/phases.tsv" "$W/train.log" "$OUT/" 2>/dev/null || true
    tar -czf "$OUT/results.tgz" -C "$W" phases.tsv train.log runs/$RUN/train.csv runs/$RUN/validation.csv runs/$RUN/run.json \
      eval_$RUN/eval.json eval_$RUN/eval.md eval_$RUN/episodes.jsonl 2>/dev/null || true
    cp "$OUT/results.tgz" "$W/" 2>/dev/null || true
    ls -l "$OUT"
    ;;
  weights)  # weight pieces FIRST..FIRST+COUNT-1 (float16, 15 MiB each; at most 7 per call) and, with 0, the config
    first=$2 count=$3
    [ -d "$W/export/$RUN" ] || python3 scripts/gpu_checkpoint.py shrink "$W/runs/$RUN" "$W/export/$RUN"
    mkdir -p "$OUT/$RUN"
    for i in $(seq "$first" $((first + count - 1))); do
      piece=$(printf "%s/export/%s/weights.part%03d" "$W" "$RUN" "$i")
      [ -f "$piece" ] && cp "$piece" "$OUT/$RUN/"
    done
    if [ "$first" = 0 ]; then tar -cf "$OUT/$RUN/meta.tar" -C "$W/export/$RUN" $(cd "$W/export/$RUN" && ls | grep -v weights.part); fi
    ls -l "$OUT/$RUN"
    break
    ;;
  *)
    echo "usage: $0 stash|setup|bench|record|train|wait|eval|results|weights FIRST COUNT" >&2
    exit 2
    ;;
  esac
done
