#!/usr/bin/env bash
# The runs behind docs/RESULTS.md v2 beyond the first one-box run, on one machine with two GPUs (2 x NVIDIA
# H200, 32 CPU cores, no network access): record 8 tasks x 25 demos and held-out insert_peg/plug_charger demos (seeds 30000+);
# train the 25-demo model's second seed on both GPUs (torchrun, the paper's batch 192 = 2 x 96); time the
# loop on one GPU against it and check kill-and-resume on two ranks (benchmarks/ddp_bench.py); then the
# 10-demo model and the 10-demo single-camera model, one per GPU at the same time (half the steps, as the
# v1 10-demo run: steps in proportion to the data), while the second seed is evaluated; evaluate every
# model closed-loop on seeds 10000-10049 and offline on the held-out demos.
#
# On a two-GPU workstation with rvt2 and its simulator installed: `bash scripts/offline-gpu-host/gpu_results_v2.sh all`
# (about 30 minutes on 2 x H200). On a GPU machine without network access, one command per step: `stash`
# for each .gpu/site.part.* piece but the last (pack_gpu_wheels.sh), `start` carrying the last piece and
# .gl (it starts the chain in the background), then `collect` until it has everything (each waits up to
# 9 minutes). Measured on 2 x H200 (2026-11-22): training seed 1 354 s, the DDP benchmark 242 s,
# evaluating 8 x 50 episodes 116 s; recording 200 demos with 28 workers did not end inside one 10-minute
# command, although all 200 files were written (see docs/BENCHMARKS.md, "Several GPUs").
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
export WORKERS=${WORKERS:-28}
self=scripts/offline-gpu-host/$(basename "$0")
onebox=scripts/offline-gpu-host/gpu_onebox.sh
case ${1:-all} in
  stash) bash $onebox stash ;;
  start) bash $onebox stash setup
         bash $onebox bg chain "$self" chain ;;  # the chain below, in the background (commands end at 10 minutes)
  chain) bash $onebox record heldout
         RUN=seed1 NPROC=2 TRAIN_ARGS="--compile --seed 1" bash $onebox train ddpbench
         RUN=demos10 STEPS=550 TRAIN_ARGS="--compile --episodes-per-task 10" CUDA_VISIBLE_DEVICES=0 bash $onebox bg demos10 train
         RUN=front10 STEPS=550 TRAIN_ARGS="--compile --episodes-per-task 10 --cameras front" CUDA_VISIBLE_DEVICES=1 \
           bash $onebox bg front10 train
         RUN=seed1 bash $onebox eval offline
         WAIT_S=100000 bash $onebox wait demos10 wait front10
         for run in demos10 front10; do RUN=$run bash $onebox eval offline; done ;;
  collect) WAIT_S=${WAIT_S:-540} bash $onebox wait chain || true
           RUNS="seed1 demos10 front10" bash $onebox results ;;
  all) bash $onebox setup && bash "$self" chain && RUNS="seed1 demos10 front10" bash $onebox results ;;
  *) echo "usage: $0 stash|start|chain|collect|all" >&2; exit 2 ;;
esac
