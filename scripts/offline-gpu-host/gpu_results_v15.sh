#!/usr/bin/env bash
# Results v15 (docs/RESULTS.md): the 10-demo recipe of results v11-v14 trained on demos of pick_cube's own
# expert (rvt2cli.record.experts:pick_cube: the cube lifted 10 cm and drawn 20 cm towards the robot's base
# before the carry, so the arm does not hide the goal sphere when the carry is decided). Everything else
# as v12_10 (training seed 0): gpu_results_v11.sh with EPISODES=10 RUN=v15_10, pick_cube evaluated first
# among the other tasks.
#
# On a workstation with rvt2 and its simulator installed: `bash scripts/offline-gpu-host/gpu_results_v15.sh all`.
# On a GPU machine without network access (commands of at most 10 minutes), as run: `stash` three times,
# carrying .gpu/site.part.aa, .ab, .ac one per command, then `start` carrying .gpu/site.part.ad,
# .gpu/site.sha256 and .gl, then `collect` until the log says the chain is done (29 minutes on one H100
# with 16 cores, recording to evaluation). `replicate start|collect|all` trains and evaluates the same recipe
# with training seed 1 (RUN=v15_10_seed1), on a second machine the same way.
set -euo pipefail
cd "$(dirname "$0")/../.."   # the repository root
export EPISODES=10 RUN=${RUN:-v15_10} CHAIN=through
export OTHERS=${OTHERS:-pick_cube,place_sphere,lift_peg_upright,stack_cube,push_cube,pull_cube}
case ${1:-} in
  stash|start|collect|all) bash scripts/offline-gpu-host/gpu_results_v11.sh "$1" ;;
  replicate)  # v14's replicate (the same recipe with --seed 1), on these demos and under this name
    REPLICATE=${REPLICATE:-v15_10_seed1} bash scripts/offline-gpu-host/gpu_results_v14.sh replicate "${2:-all}" ;;
  *) echo "usage: $0 stash|start|collect|all|replicate [start|collect|all]" >&2; exit 2 ;;
esac
