#!/usr/bin/env bash
# Results v13 (docs/RESULTS.md): stage 2's 3D argmax looks only where training puts stage 2's targets
# (ModelConfig.stage2_window: within +-5 cm of its +-10 cm box). Two trained models, unchanged, evaluated
# again on all 8 tasks, 50 seeds per task from 10000: first the 10-demo model of results v12 (run v12_10,
# report eval_v13_10), then the 25-demo model of results v11 (run v11, report eval_v13).
#
# The weights: each run's float16 pieces (gpu_checkpoint.py shrink; 10 pieces and meta.tar, about 150 MiB)
# restored by `gpu_onebox.sh restore`.
# `baseline` evaluates both again as before, with the whole box searched (stage2_window = 1.0, set in a copy of
# each run, `${RUN}_full`): the same machine, the same seeds (eval_v13_full_10, eval_v13_full).
# `cpugpu` asks why the 10-demo model acts differently on a CPU-only machine: its whole-box run on push_cube
# and pull_cube with TF32 off in cuBLAS and cuDNN (NVIDIA_TF32_OVERRIDE=0; eval_v13_full_10_notf32), as it
# was (eval_v13_full_10_again: the same episodes?), and with the policy on this machine's CPU while the
# simulator renders on its GPU (eval_v13_full_10_cpupolicy). `lavapipe` runs it once more with the policy on
# the GPU and the simulator's cameras rendered by Mesa's lavapipe, as on a machine without a GPU
# (eval_v13_full_10_lavapipe); `packlvp`, on a Debian 12 machine where `make setup` installed lavapipe,
# packs it with the libraries it needs that a GPU image may lack into .gpu/lvp.tar.xz (42 MB) to carry.
# On a workstation with rvt2 and its simulator installed and both runs in $W/runs/:
#   bash scripts/offline-gpu-host/gpu_results_v13.sh all
# On a GPU machine without network access (64 MiB carried per command), as run: `stash` once per carry,
# carrying .gpu/site.part.aa, .ab, .ac, then v11's pieces in .gpu/weights_a/ (parts 000-002, with meta.tar's
# config.json, manifest.json and instructions.safetensors), .gpu/weights_b/ (003-005), .gpu/weights_c/
# (006-008), then v12_10's the same way in .gpu/tendemo_a/ .. _c/; then `evaluate`, carrying
# .gpu/site.part.ad, .gpu/site.sha256, .gl, .gpu/weights_d/ and .gpu/tendemo_d/ (009); then `collect` until
# the log says both evaluations are done (about 5 minutes each on one GPU with 16 cores).
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
onebox=scripts/offline-gpu-host/gpu_onebox.sh
self=scripts/offline-gpu-host/$(basename "$0")
export W=${W:-/tmp/w} WORKERS=${WORKERS:-14}
TEN=${TEN:-v12_10} TWENTYFIVE=${TWENTYFIVE:-v11}
RUNS="v13_10 v13 v13_full_10 v13_full"

full_box() {  # RUN -> ${RUN}_full: the same weights, stage 2 searching its whole box
  rm -rf "$W/runs/${1}_full" && cp -r "$W/runs/$1" "$W/runs/${1}_full"
  for c in "$W/runs/${1}_full"/checkpoints/*/config.json; do
    python3 -c "import json, sys; c = json.load(open(sys.argv[1])); c['model']['stage2_window'] = 1.0; json.dump(c, open(sys.argv[1], 'w'), indent=2)" "$c"
  done
}

case ${1:-} in
  stash)
    PIECES=.gpu/weights WEIGHTS=$W/weights_$TWENTYFIVE bash $onebox stash
    PIECES=.gpu/tendemo WEIGHTS=$W/weights_$TEN bash $onebox stash ;;
  evaluate)  # unpack, restore both runs, evaluate in the background
    bash "$self" stash
    RUN=$TWENTYFIVE WEIGHTS=$W/weights_$TWENTYFIVE bash $onebox setup restore
    RUN=$TEN WEIGHTS=$W/weights_$TEN bash $onebox restore
    bash $onebox bg eval "$self" evalchain ;;
  evalchain)
    RUN=$TEN EVAL_NAME=v13_10 bash $onebox eval || echo "evaluating $TEN failed"
    RUN=$TWENTYFIVE EVAL_NAME=v13 bash $onebox eval || echo "evaluating $TWENTYFIVE failed" ;;
  baseline)  # after evaluate (the runs restored): both runs with the whole box, in the background
    full_box "$TEN" && full_box "$TWENTYFIVE"
    bash $onebox bg base "$self" basechain ;;
  basechain)
    RUN=${TEN}_full EVAL_NAME=v13_full_10 bash $onebox eval || echo "evaluating ${TEN}_full failed"
    RUN=${TWENTYFIVE}_full EVAL_NAME=v13_full bash $onebox eval || echo "evaluating ${TWENTYFIVE}_full failed" ;;
  cpugpu)  # after the 10-demo run's stash, setup and restore
    full_box "$TEN"
    pushpull="--tasks push_cube,pull_cube"
    NVIDIA_TF32_OVERRIDE=0 RUN=${TEN}_full EVAL_NAME=v13_full_10_notf32 EVAL_ARGS=$pushpull bash $onebox eval
    RUN=${TEN}_full EVAL_NAME=v13_full_10_again EVAL_ARGS=$pushpull bash $onebox eval
    DEVICE=cpu RUN=${TEN}_full EVAL_NAME=v13_full_10_cpupolicy EVAL_ARGS=$pushpull bash $onebox eval ;;
  packlvp)  # here, on the development machine
    rm -rf /tmp/lvp && mkdir -p /tmp/lvp/lib
    lvp=/usr/lib/x86_64-linux-gnu/libvulkan_lvp.so
    cp -L "$lvp" /tmp/lvp/lib/
    # its libraries, less those every Python image has (a second copy of those would shadow the image's own)
    ldd "$lvp" | awk '{print $3}' | grep '^/' \
      | grep -v -E '/(libc|libm|libpthread|libdl|librt|ld-linux|libgcc_s|libstdc\+\+|liblzma|libz|libzstd|libexpat|libffi|libbsd|libmd|libtinfo)\.so' \
      | xargs -I{} cp -L {} /tmp/lvp/lib/
    python3 -c "import json; json.dump({'file_format_version': '1.0.0', 'ICD': {'api_version': '1.3.0', 'library_path': '/tmp/lvp/lib/libvulkan_lvp.so'}}, open('/tmp/lvp/lvp_icd.json', 'w'))"
    mkdir -p .gpu && tar -C /tmp -cf - lvp | xz -T0 -6 > .gpu/lvp.tar.xz && ls -l .gpu/lvp.tar.xz ;;
  lavapipe)  # after the 10-demo run's stash, setup and restore, carrying .gpu/lvp.tar.xz
    full_box "$TEN"
    rm -rf /tmp/lvp && tar -xJf .gpu/lvp.tar.xz -C /tmp
    mkdir -p /usr/share/vulkan/icd.d && cp /tmp/lvp/lvp_icd.json /usr/share/vulkan/icd.d/lvp_icd.json
    export RVT2_VULKAN=lavapipe
    export LD_LIBRARY_PATH=/tmp/lvp/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
    PYTHONPATH=${SITE:-/tmp/site}:$PWD python3 -m rvt2cli doctor 2>&1 | grep -i vulkan || true   # which driver renders
    RUN=${TEN}_full EVAL_NAME=v13_full_10_lavapipe EVAL_ARGS="--tasks push_cube,pull_cube" bash $onebox eval ;;
  collect)
    WAIT_S=${WAIT_S:-540} bash $onebox wait ${WAIT_FOR:-eval} || true
    RUNS=$RUNS bash $onebox results ;;
  all)
    bash $onebox setup && bash "$self" evalchain && full_box "$TEN" && full_box "$TWENTYFIVE" && bash "$self" basechain
    RUNS=$RUNS bash $onebox results ;;
  *) echo "usage: $0 stash|evaluate|evalchain|baseline|basechain|cpugpu|packlvp|lavapipe|collect|all" >&2; exit 2 ;;
esac
