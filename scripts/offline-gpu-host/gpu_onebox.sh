#!/usr/bin/env bash
# rvt2's phases on one GPU machine without network access (python3 3.12 with CUDA torch and numpy 2, 64 MiB
# carried in per transfer, at most 10 minutes per command, /tmp kept between commands while the machine
# stays up). On a GPU workstation with rvt2 installed, run `python -m benchmarks.experiment` directly.
#
# Online:  bash scripts/offline-gpu-host/pack_gpu_wheels.sh  # -> .gpu/site.part.* (sized to the tree) + site.sha256
# Offline host, one command per line, each carrying the parts not sent yet (and .gl, the GL/Vulkan loaders);
# K=scripts/offline-gpu-host, E=experiments/rvt2_25demos.toml:
#   bash $K/gpu_onebox.sh stash                         # keep the carried parts in /tmp/w
#   bash $K/gpu_onebox.sh stash setup bg main experiment $E all > bg.log 2>&1   # unpack, then every phase in the background
#   WAIT_S=540 bash $K/gpu_onebox.sh wait main          # repeat until it reports
#   EXPERIMENT=$E bash $K/gpu_onebox.sh results         # logs and reports -> $OUT/results.tgz
#   RUN_DIR=/tmp/w/rvt2_25demos/runs/seed0 bash $K/gpu_onebox.sh weights 0 4   # float16 weight pieces 0-3 (and meta.tar)
# Online:  tar -xf meta.tar in the pieces' folder; python $K/gpu_checkpoint.py restore PIECES_DIR runs/NAME
# Weights trained elsewhere: carry their pieces as .gpu/weights*/, then `stash setup restore` with RUN_DIR set to
# the experiment's run folder, and `experiment $E eval,offline`.
#
# Phases: stash, setup, experiment FILE PHASES (benchmarks/experiment.py: record, heldout, train, eval,
# offline, oracle, or all), results, weights FIRST COUNT, restore, bg NAME PHASE... / wait NAME; and the
# building blocks of the benchmarks: untiltrain, bench, servebench, evalsharebench, record, keyframes, merged, heldout, train,
# loopbench, memorybench, ddpbench, eval, oracle, replay, repro, offline, recordbench, capturebench, recordprofile,
# evalprofile, capturetests, gputests.
# Settings (environment): EXPERIMENT_ARGS (more options of benchmarks/experiment.py, e.g. "--training-seeds 1"),
# EXPERIMENT_FOLDER (the experiment's folder in $W instead of the file's name), BENCH_ARGS (more options of `bench`),
# NPROC (GPUs to train on), WORKERS (simulator processes), DEVICE, RUN_DIR (the run weights and restore use),
# PIECES and WEIGHTS (carried weight pieces, and where stash keeps them for restore), EXTRA_PYTHONPATH (a folder
# searched first, e.g. a sitecustomize.py); for the building blocks EPISODES (per task), TASK_SET (recordbench),
# RUN, BATCH (global), STEPS, TRAIN_ARGS, DATA, MEMORYBENCH_ARGS, OFFLINE_DEMOS, EVAL_EPISODES, EVAL_ARGS, EVAL_NAME and RUNS (results),
# SHARE_EPISODES (per task), SHARE_KEYFRAMES (the keyframe budget) and SHARE_CHECKPOINT (a trained run) for evalsharebench;
# EXACT=1: `weights` sends float32 weights as trained (an evaluation to be resumed elsewhere: 25 pieces for rvt2-18);
# RESUMABLE=1: also the training state and the run's logs (a training stopped by --time-limit, resumed elsewhere).
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root: every path below is relative to it
KIT=scripts/offline-gpu-host
W=${W:-/tmp/w}
SITE=${SITE:-/tmp/site}
WORKERS=${WORKERS:-14}
EPISODES=${EPISODES:-25}
TASKS=${TASKS:-"insert_peg plug_charger place_sphere lift_peg_upright stack_cube pick_cube push_cube pull_cube"}
RUN=${RUN:-onebox}
BATCH=${BATCH:-192}
STEPS=${STEPS:-1100}
NPROC=${NPROC:-1}
EVAL_EPISODES=${EVAL_EPISODES:-50}
RUNS=${RUNS:-$RUN}
RUN_DIR=${RUN_DIR:-$W/runs/$RUN}   # the run folder `weights` takes pieces from and `restore` writes
PIECES=${PIECES:-.gpu/weights}     # a run's carried weight pieces: the folders $PIECES*/
WEIGHTS=${WEIGHTS:-$W/weights}     # where stash keeps them and restore reads them
HELDOUT=${HELDOUT:-data/heldout}   # held-out demos (recorded here with seeds the training never saw), carried in
CONFIG=${CONFIG:-rvt2}
DEVICE=${DEVICE:-cuda}
WAIT_S=${WAIT_S:-560}   # how long `wait` waits inside one command
OUT=${OUT:-/tmp/rvt2-out}
mkdir -p "$W" "$OUT"
export PYTHONPATH=${EXTRA_PYTHONPATH:+$EXTRA_PYTHONPATH:}$SITE:$PWD PYTHONUNBUFFERED=1 HF_HUB_OFFLINE=1
# the packed instruction embeddings, once setup has unpacked them (an installed rvt2 embeds its own)
if [ -f "$SITE/embeddings.safetensors" ]; then export RVT2_EMBEDDINGS=$SITE/embeddings.safetensors; fi
# toppra's docstrings hold invalid escapes that Python 3.12 reports while compiling them, in every process
export PYTHONWARNINGS=${PYTHONWARNINGS:-ignore::SyntaxWarning}
export LD_LIBRARY_PATH=${LD_LIBRARY_PATH:-}:/usr/local/nvidia/lib64:/usr/local/nvidia/lib
export PYTORCH_CUDA_ALLOC_CONF=${PYTORCH_CUDA_ALLOC_CONF:-expandable_segments:True}  # two trainings share one GPU
export RVT2_VULKAN=${RVT2_VULKAN:-nvidia}   # the point of this machine: say so at once if its GPU cannot render
# the carried lavapipe's libraries (pack_lavapipe.sh; only those this host lacks): RVT2_VULKAN=lavapipe, or an
# experiment file's `renderer = "lavapipe"`, renders on the CPU with it once setup has unpacked it
export LD_LIBRARY_PATH=$LD_LIBRARY_PATH:$SITE/lavapipe/lib
RVT2=(python3 -m rvt2cli)
# run from this source tree: the package finds tasks/ and schemas/ where an install would put them
# (each command may get a fresh copy of the tree, so every command links them)
ln -sfn ../tasks rvt2cli/_tasks && ln -sfn ../schemas rvt2cli/_schemas
clock() { date +%s; }
progress() {  # how far the work in $W has come: demos recorded, each training's last row, each evaluation's episodes
  shopt -s nullglob
  local demos=("$W"/demos/*.mcap "$W"/*/demos/*.mcap)
  echo "demos: ${#demos[@]}"
  for f in "$W"/runs/*/train.csv "$W"/*/runs/*/train.csv; do  # its last row's step, samples/s and steps skipped
    IFS=, read -r step _ _ _ _ _ _ _ _ _ _ rate skipped _ < <(tail -1 "$f" | tr -d '\r')
    echo "$f: step $step, ${rate%.*} samples/s, $skipped skipped"
  done
  for j in "$W"/eval_*/episodes.jsonl "$W"/*/evals/*/episodes.jsonl; do echo "$j: $(( $(wc -l < "$j") - 1 )) episodes"; done
  shopt -u nullglob
}
phase() {  # NAME SECONDS: one line per phase in $W/phases.tsv
  printf '%s\t%.1f\n' "$1" "$2" | tee -a "$W/phases.tsv"
}

while [ $# -gt 0 ]; do
  step=$1
  shift
  case $step in
  stash)
    cp .gpu/site.part.* .gpu/site.sha256 .gpu/lavapipe.tar.xz "$W/" 2>/dev/null || true
    # a run's weight pieces (`weights` on another machine, then `tar -xf meta.tar`), carried as $PIECES*/
    for d in "$PIECES"*/; do
      if [ -d "$d" ]; then mkdir -p "$WEIGHTS" && cp "$d"* "$WEIGHTS/"; fi
    done
    if [ -d "$HELDOUT" ]; then mkdir -p "$W/heldout" && cp "$HELDOUT"/* "$W/heldout/"; fi
    ls -l "$W"
    ;;
  setup)
    t=$(clock)
    if [ ! -f "$SITE/.unpacked" ] && [ ! -f "$W/site.sha256" ]; then
      echo "no site pieces stashed in $W: using the rvt2 installed here"
    elif [ ! -f "$SITE/.unpacked" ]; then
      (cd "$W" && sha256sum -c site.sha256)
      # -T0: the stream's blocks (192 MiB each from xz -T2 -9) are unpacked side by side
      mkdir -p "$SITE" && cat "$W"/site.part.* | xz -d -T0 | tar -x -C "$SITE" && touch "$SITE/.unpacked"
      export RVT2_EMBEDDINGS=$SITE/embeddings.safetensors   # for the phases after this one in this command
    fi
    if [ -d .gl ]; then  # Vulkan and GL loaders (apt-get download, carried): the image may have none
      for f in .gl/*.deb; do dpkg -x "$f" /; done
      ldconfig
    fi
    if [ -f "$W/lavapipe.tar.xz" ] && [ ! -f "$SITE/lavapipe/lvp_icd.json" ]; then
      mkdir -p "$SITE/lavapipe" && tar -xJf "$W/lavapipe.tar.xz" -C "$SITE/lavapipe"
      # only the libraries this host lacks: its own copies (newer) must not be shadowed
      known=$(ldconfig -p)
      for lib in "$SITE"/lavapipe/lib/*.so.*; do
        if grep -q "^[[:space:]]$(basename "$lib") " <<< "$known"; then rm "$lib"; fi
      done
      # its manifest where rvt2 looks for lavapipe, the library named by its path here
      mkdir -p /usr/share/vulkan/icd.d
      python3 - "$SITE/lavapipe" /usr/share/vulkan/icd.d/lvp_icd.json <<'PY'
import json, sys
icd = json.load(open(f"{sys.argv[1]}/lvp_icd.json"))
icd["ICD"]["library_path"] = f"{sys.argv[1]}/lib/libvulkan_lvp.so"
json.dump(icd, open(sys.argv[2], "w"))
PY
      echo "lavapipe: $(ls "$SITE/lavapipe/lib" | wc -l) libraries kept in $SITE/lavapipe/lib"
    fi
    # kept in $W for `results` ($OUT is emptied before every command)
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$W/gpu.txt"
    "${RVT2[@]}" doctor | tee -a "$W/gpu.txt"
    if grep -q MISSING "$W/gpu.txt"; then  # a stale site: the phases that import it fail later, not here
      echo "setup: WARNING: the carried site lacks a library rvt2 loads (MISSING above): run pack_gpu_wheels.sh again"
    fi
    cp "$W/gpu.txt" "$OUT/"
    phase setup $(( $(clock) - t ))
    ;;
  bench)  # the training step rvt2 train runs, at the paper's batch and the one we train with
    t=$(clock)
    # in $W (which `bg` keeps), named by the compile mode in BENCH_ARGS: several modes, one after another
    mode=$(echo "${BENCH_ARGS:-}" | sed -n 's/.*--compile-mode \([a-z-]*\).*/_\1/p')
    # shellcheck disable=SC2086  # BENCH_ARGS is a list of options (e.g. "--compile-mode reduce-overhead")
    python3 -m benchmarks.policy_bench --configs rvt2 --batch "24,$BATCH" --compile --skip-inference --steps 15 \
      --json "$W/policy_bench$mode.json" ${BENCH_ARGS:-} 2>&1 | tail -6
    cp "$W/policy_bench$mode.json" "$OUT/" 2>/dev/null || true
    phase "bench$mode" $(( $(clock) - t ))
    ;;
  servebench)  # rvt2 serve under 1, 4 and 16 client processes, with and without batching (benchmarks/serve_bench.py)
    t=$(clock)
    python3 -m benchmarks.serve_bench --device "$DEVICE" --config "$CONFIG" ${SERVEBENCH_ARGS:-} --json "$W/serve_bench.json" 2>&1 | tail -12
    phase servebench $(( $(clock) - t ))
    ;;
  untiltrain)  # wait until a training in $W writes its first train.csv row: side phases on a free GPU start after recording
    until ls "$W"/*/runs/*/train.csv >/dev/null 2>&1; do sleep 10; done
    ;;
  evalsharebench)  # an evaluation's WORKERS sharing one policy (--shared-policy) against one each (benchmarks/eval_share_bench.py)
    t=$(clock)
    # SHARE_CHECKPOINT: a trained run (realistic keyframes per episode) instead of random weights of CONFIG
    model=(--random "$CONFIG"); if [ -n "${SHARE_CHECKPOINT:-}" ]; then model=(--checkpoint "$SHARE_CHECKPOINT"); fi
    python3 -m benchmarks.eval_share_bench "${model[@]}" --tasks "$(echo $TASKS | tr ' ' ,)" --episodes "${SHARE_EPISODES:-2}" \
      --workers "$WORKERS" --device "$DEVICE" --keyframe-budget "${SHARE_KEYFRAMES:-10}" --json "$W/eval_share_bench.json" 2>&1 | tail -4
    phase evalsharebench $(( $(clock) - t ))
    ;;
  record)
    t=$(clock)
    "${RVT2[@]}" record --task "$(echo $TASKS | tr ' ' ,)" --episodes "$EPISODES" --workers "$WORKERS" --out "$W/demos" \
      --no-progress 2>&1 | tail -20
    phase record $(( $(clock) - t ))
    ;;
  keyframes)  # the rule again over $W/demos (`rvt2 record` annotated them as it wrote them)
    t=$(clock)
    "${RVT2[@]}" extract-keyframes "$W/demos" 2>&1 | tail -1
    phase keyframes $(( $(clock) - t ))
    ;;
  merged)  # a copy of the demos and held-out demos (MERGE_DIRS) whose keyframe refinements under MERGE_MM are merged
    t=$(clock)
    for d in ${MERGE_DIRS:-demos heldout}; do
      [ -d "$W/$d" ] || continue
      rm -rf "$W/${d}_merged" && cp -r "$W/$d" "$W/${d}_merged"
      "${RVT2[@]}" extract-keyframes "$W/${d}_merged" --merge-refinements "${MERGE_MM:-30}" | tail -1
    done
    phase merged $(( $(clock) - t ))
    ;;
  restore)  # a run's weights from the pieces stash kept in $WEIGHTS (another machine trained it) into RUN_DIR
    python3 $KIT/gpu_checkpoint.py restore "$WEIGHTS" "$RUN_DIR"
    ;;
  experiment)  # experiment FILE PHASES: an experiment file's phases (comma-separated, or all) into $W/NAME
    file=$1 phases=$2   # EXPERIMENT_FOLDER: another folder name in $W than the file's (e.g. NAME_3500steps)
    shift 2
    t=$(clock)
    folder=${EXPERIMENT_FOLDER:-$(basename "$file" .toml)}
    # shellcheck disable=SC2086  # EXPERIMENT_ARGS is a list of options
    python3 -m benchmarks.experiment "$file" --run --phase "$phases" --out "$W/$folder" \
      --rvt2 "python3 -m rvt2cli" --torchrun "python3 -m torch.distributed.run" --workers "$WORKERS" --gpus "$NPROC" \
      --device "$DEVICE" ${EXPERIMENT_ARGS:-} 2>&1 | tee -a "$W/experiment_$folder.log"
    phase "experiment_${folder}_$phases" $(( $(clock) - t ))
    ;;
  oracle)  # the executor's ceiling on the evaluation seeds: the expert's keyframes, closed loop
    t=$(clock)
    "${RVT2[@]}" eval --oracle --tasks "$(echo $TASKS | tr ' ' ,)" --episodes "$EVAL_EPISODES" --seed 10000 \
      --workers "$WORKERS" --out "$W/eval_oracle" --no-progress 2>&1 | tail -10
    phase oracle $(( $(clock) - t ))
    ;;
  replay)  # a recorded evaluation's predicted keyframes through today's executor (REPLAY: its journal)
    t=$(clock)
    "${RVT2[@]}" eval --replay "${REPLAY:?give REPLAY=JOURNAL, the episodes.jsonl of a recorded evaluation}" \
      --tasks "${REPLAY_TASKS:-insert_peg,plug_charger,lift_peg_upright}" --episodes "$EVAL_EPISODES" --seed 10000 \
      --workers "$WORKERS" --out "$W/eval_replay" --no-progress 2>&1 | tail -5
    phase replay $(( $(clock) - t ))
    ;;
  recordbench)  # recording's cost: EPISODES successful demos of every task of TASK_SET, WORKERS workers, for each capture path of RECORDBENCH_CAPTURES
    t=$(clock)
    for capture in ${RECORDBENCH_CAPTURES:-${RVT2_CAPTURE:-auto}}; do   # auto: a camera group where CUDA renders; cameras: one by one
      RVT2_CAPTURE=$capture python3 -m benchmarks.record_bench --task-set "${TASK_SET:-rlbench18}" --seeds 0 --episodes "$EPISODES" \
        --workers "$WORKERS" --json "$W/record_bench_${TASK_SET:-rlbench18}_$capture.json" 2>&1 | tail -3
    done
    phase recordbench $(( $(clock) - t ))
    ;;
  capturebench)  # the cameras' capture: capture_cameras against SAPIEN's camera groups, 1 and many processes
    t=$(clock)
    python3 -m benchmarks.capture_bench --task "${CAPTURE_TASK:-open_drawer}" --processes "${CAPTURE_PROCESSES:-1,8,15}" \
      --scenes "${CAPTURE_SCENES:-1,8}" --json "$W/capture_bench.json" 2>&1 | tail -14
    phase capturebench $(( $(clock) - t ))
    ;;
  recordprofile)  # where a demo's core-seconds go: PROFILE_DEMOS demos of every task of TASK_SET, one process, for each
                  # capture path of PROFILE_CAPTURES (auto: a camera group where CUDA renders; cameras: one by one)
    t=$(clock)
    for capture in ${PROFILE_CAPTURES:-auto}; do
      RVT2_CAPTURE=$capture python3 -m benchmarks.record_bench --task-set "${TASK_SET:-rlbench18}" --profile "${PROFILE_DEMOS:-2}" \
        --json "$W/record_profile_$capture.json" 2>&1 | tail -14
    done
    phase recordprofile $(( $(clock) - t ))
    ;;
  capturetests)  # the camera group against camera by camera, on this GPU (tests/test_capture.py; skipped without one)
    t=$(clock)
    python3 -m pytest -q -p no:cacheprovider tests/test_capture.py 2>&1 | tail -15 | tee "$W/capture_tests.txt"
    phase capturetests $(( $(clock) - t ))
    ;;
  gputests)  # every test CI skips for want of CUDA or NVIDIA rendering (capture, serving's fixed batch, eval's CUDA graph)
    t=$(clock)
    python3 -m pytest -q -p no:cacheprovider -rs tests/test_capture.py tests/test_serve.py tests/test_eval.py -k "capture or gpu or cuda" 2>&1 \
      | tail -20 | tee "$W/gpu_tests.txt"
    phase gputests $(( $(clock) - t ))
    ;;
  evalprofile)  # where an evaluation episode's core-seconds go: rvt2-18's recorded predictions replayed, one process
    t=$(clock)
    python3 -m benchmarks.eval_bench benchmarks/results/rvt2_18/eval_partial/episodes.jsonl.xz \
      benchmarks/results/rvt2_18/cpu_preview/episodes.jsonl.xz --episodes "${PROFILE_EPISODES:-1}" \
      --json "$W/eval_profile.json" 2>&1 | tail -34
    phase evalprofile $(( $(clock) - t ))
    ;;
  heldout)  # held-out demos for offline scores: HELDOUT_TASKS x 5 from seed 30000 (training demos use 0 upwards)
    t=$(clock)
    "${RVT2[@]}" record --task "$(echo ${HELDOUT_TASKS:-$TASKS} | tr ' ' ,)" --episodes "${HELDOUT_EPISODES:-5}" --seed 30000 \
      --workers "$WORKERS" --out "$W/heldout" --no-progress 2>&1 | tail -1
    phase heldout $(( $(clock) - t ))
    ;;
  train)  # RUN on NPROC GPUs (torchrun when more than one), BATCH samples per step in all
    t=$(clock)
    rm -rf "$W/runs/$RUN"
    launch=("${RVT2[@]}")
    if [ "$NPROC" -gt 1 ]; then launch=(python3 -m torch.distributed.run --standalone --nproc-per-node "$NPROC" -m rvt2cli); fi
    # shellcheck disable=SC2086  # TRAIN_ARGS is a list of options
    "${launch[@]}" train --data "${DATA:-$W/demos}" --out "$W/runs/$RUN" --config "$CONFIG" --batch-size $((BATCH / NPROC)) \
      --steps "$STEPS" --warmup $((STEPS / 10)) --val-episodes 1 --val-every $((STEPS / 4)) --save-every $((STEPS / 4)) \
      --no-progress ${TRAIN_ARGS---compile} 2>&1 | tee "$W/train_$RUN.log" | grep -v "^step " | tail -4
    phase "train_$RUN" $(( $(clock) - t ))
    tail -1 "$W/runs/$RUN/train.csv"
    ;;
  loopbench)  # the training loop against its step on the recorded demos (benchmarks/loop_bench.py)
    t=$(clock)
    # every 4th demo file: the loop's speed does not depend on how many samples it draws from
    python3 -m benchmarks.loop_bench --data $(ls "$W"/demos/*.mcap | awk 'NR % 4 == 1') --config "$CONFIG" --batch-size "$BATCH" ${LOOPBENCH_ARGS---compile} --steps 20 --profile "$W/profile" \
      --json "$W/loop_bench.json" > "$W/loop_bench.log" 2>&1 || echo "loop_bench failed (the chain goes on): see loop_bench.log"
    grep -v "^data:" "$W/loop_bench.log" | tail -24
    phase loopbench $(( $(clock) - t ))
    ;;
  memorybench)  # rvt2 train with the clouds on the GPU, on the host, and on the host in micro-batches (benchmarks/memory_bench.py)
    t=$(clock)
    # DATA: a sample cache (rvt2 pack-samples) or demos; by default every 4th demo file, as loopbench
    # shellcheck disable=SC2086  # DATA and MEMORYBENCH_ARGS are lists
    python3 -m benchmarks.memory_bench --data ${DATA:-$(ls "$W"/demos/*.mcap | awk 'NR % 4 == 1')} --config "$CONFIG" \
      --batch-size "$BATCH" ${MEMORYBENCH_ARGS:-} --json "$W/memory_bench.json" > "$W/memory_bench.log" 2>&1 \
      || echo "memory_bench failed (the chain goes on): see memory_bench.log"
    grep -v "^data:" "$W/memory_bench.log" | tail -12
    cp "$W/memory_bench.json" "$OUT/" 2>/dev/null || true
    phase memorybench $(( $(clock) - t ))
    ;;
  repro)  # RUN's evaluation again on REPRO_TASKS x REPRO_EPISODES: the same episodes, record for record?
    t=$(clock)
    tasks=${REPRO_TASKS:-insert_peg,plug_charger,lift_peg_upright}
    "${RVT2[@]}" eval --checkpoint "$W/runs/$RUN" --tasks "$tasks" --episodes "${REPRO_EPISODES:-10}" --seed 10000 \
      --workers "$WORKERS" --device "$DEVICE" --out "$W/eval_${RUN}_repro" --no-progress 2>&1 | tail -4
    python3 scripts/compare_evals.py "$W/eval_$RUN" "$W/eval_${RUN}_repro" | tee "$W/eval_${RUN}_repro/compare.txt"
    phase "repro_$RUN" $(( $(clock) - t ))
    ;;
  ddpbench)  # the training loop on 1 GPU against RUN's NPROC GPUs at the same per-GPU batch; kill-and-resume
    t=$(clock)
    [ -f "$W/samples.safetensors" ] || "${RVT2[@]}" pack-samples "$W/demos" --out "$W/samples.safetensors" --no-progress
    python3 -m benchmarks.ddp_bench --data "$W/samples.safetensors" --gpus "$NPROC" --batch-size $((BATCH / NPROC)) --compile \
      --steps 100 --multi-gpu-run "$W/runs/$RUN" --resume-check --work "$W/ddp" --json "$W/ddp_bench.json" 2>&1 | tail -30
    phase ddpbench $(( $(clock) - t ))
    ;;
  bg)  # bg NAME PHASE...: run these phases in the background (from a copy of this tree); `wait NAME` waits
    name=$1
    shift
    rm -rf "$W/bg_$name" "$W/$name.done"
    mkdir -p "$W/bg_$name" && tar -cf - --exclude=./.gpu --exclude=./data . | tar -x -C "$W/bg_$name"
    command="$KIT/gpu_onebox.sh $*"
    if [ -f "${1:-}" ]; then command="$*"; fi  # bg NAME SCRIPT ARGS...: another script
    (cd "$W/bg_$name" && setsid nohup bash -c "t=\$(date +%s); bash $command; echo \$? \$(( \$(date +%s) - t )) > $W/$name.done" \
      > "$W/$name.log" 2>&1 < /dev/null &)
    sleep "${START_WAIT:-5}"
    cat "$W/$name.log"
    break  # the rest of the command line runs in the background
    ;;
  wait)  # wait NAME: until the background phases NAME end (at most WAIT_S seconds in this command), then how far they came
    name=$1
    shift
    while [ ! -f "$W/$name.done" ] && [ "$SECONDS" -lt "$WAIT_S" ]; do sleep 5; done
    tail -25 "$W/$name.log"
    progress
    if [ ! -f "$W/$name.done" ]; then echo "$name still running"; exit 3; fi
    read -r rc _ < "$W/$name.done"
    [ "$rc" = 0 ] || { echo "$name failed ($rc)"; exit 4; }
    ;;
  eval)  # RUN closed loop; EVAL_NAME names the report (eval_$EVAL_NAME, default RUN), EVAL_ARGS adds options
    t=$(clock)
    name=${EVAL_NAME:-$RUN}
    resume=()
    if [ -f "$W/eval_$name/episodes.jsonl" ]; then resume=(--resume); fi  # an interrupted evaluation: the rest of it
    # shellcheck disable=SC2086  # EVAL_ARGS is a list of options
    "${RVT2[@]}" eval --checkpoint "$W/runs/$RUN" --episodes "$EVAL_EPISODES" --seed 10000 --workers "$WORKERS" \
      --device "$DEVICE" --out "$W/eval_$name" --no-progress "${resume[@]}" ${EVAL_ARGS:-} 2>&1 | tail -12
    phase "eval_$name" $(( $(clock) - t ))
    ;;
  offline)  # millimetres on the held-out demos in $W/heldout (carried from $HELDOUT by stash, or the heldout phase)
    t=$(clock)
    "${RVT2[@]}" eval --checkpoint "$W/runs/$RUN" --offline "${OFFLINE_DEMOS:-$W/heldout}" --device "$DEVICE" --out "$W/offline_$RUN" \
      --no-progress 2>&1 | tail -12
    phase "offline_$RUN" $(( $(clock) - t ))
    ;;
  results)  # every small result in one file (the host returns at most 8 files per transfer)
    cp "$W/phases.tsv" "$OUT/" 2>/dev/null || true
    # the patterns are matched in $W below, not here
    files=(phases.tsv "policy_bench*.json" "record_bench_*.json" capture_bench.json "record_profile_*.json" eval_profile.json capture_tests.txt gpu_tests.txt memory_bench.json memory_bench.log serve_bench.json eval_share_bench.json ddp_bench.json loop_bench.json loop_bench.log profile/profile_real.txt profile/profile_loop.txt gpu.txt
           eval_oracle/eval.json eval_oracle/eval.md eval_oracle/episodes.jsonl eval_replay/eval.md eval_replay/episodes.jsonl)
    if [ -n "${EXPERIMENT:-}" ]; then  # an experiment's logs and reports (benchmarks/experiment.py's layout)
      e=$(basename "$EXPERIMENT" .toml)
      # shellcheck disable=SC2207  # the globs expand in $W, one path per line
      files+=($(cd "$W" && ls -d "experiment_$e.log" "$e/phases.tsv" "$e"/runs/*/{run.json,train.csv,validation.csv} \
                "$e"/evals/*/{eval.json,eval.md,episodes.jsonl} "$e"/offline/*/{offline.json,offline.md} \
                "$e"/oracle/{eval.json,eval.md,episodes.jsonl} 2>/dev/null || true))
    fi
    for run in $RUNS; do
      files+=("train_$run.log" "runs/$run/train.csv" "runs/$run/validation.csv" "runs/$run/run.json" "eval_$run/eval.json"
              "eval_$run/eval.md" "eval_$run/episodes.jsonl" "offline_$run/offline.json" "offline_$run/offline.md"
              "eval_${run}_repro/compare.txt" "eval_${run}_repro/episodes.jsonl")
    done
    # shellcheck disable=SC2068  # unquoted: the patterns expand among $W's files
    (cd "$W" && { ls -d ${files[@]} 2>/dev/null || true; } | tar -czf "$OUT/results.tgz" -T -)
    tar -tzf "$OUT/results.tgz"
    cp "$OUT/results.tgz" "$W/" 2>/dev/null || true
    ls -l "$OUT"
    ;;
  weights)  # pieces FIRST..FIRST+COUNT-1 in the manifest's order (15 MiB each, at most 4 per transfer: the
            # float16 weights, then the instruction embeddings) and, with 0, the config and manifest (meta.tar)
    first=$1 count=$2
    shift 2
    [ -d "$W/export/$RUN" ] || python3 $KIT/gpu_checkpoint.py shrink "$RUN_DIR" "$W/export/$RUN" ${EXACT:+--exact} \
      ${RESUMABLE:+--resumable}
    mkdir -p "$OUT/$RUN"
    mapfile -t pieces < <(python3 -c 'import json, sys; sys.path.insert(0, sys.argv[2]); from gpu_checkpoint import all_pieces
print("\n".join(all_pieces(json.load(open(sys.argv[1])))))' "$W/export/$RUN/manifest.json" "$KIT")
    for piece in "${pieces[@]:$first:$count}"; do cp "$W/export/$RUN/$piece" "$OUT/$RUN/"; done
    if [ "$first" = 0 ]; then tar -cf "$OUT/$RUN/meta.tar" -C "$W/export/$RUN" config.json manifest.json; fi
    echo "${#pieces[@]} pieces in all"
    ls -l "$OUT/$RUN"
    break
    ;;
  *)
    echo "usage: $0 stash|setup|experiment FILE PHASES|results|weights FIRST COUNT|restore|bg NAME PHASE...|wait NAME|untiltrain|bench|record|keyframes|heldout|merged|loopbench|memorybench|train|ddpbench|eval|oracle|replay|repro|offline|recordbench|capturebench|recordprofile|evalprofile|capturetests|gputests|servebench|evalsharebench" >&2
    exit 2
    ;;
  esac
done
