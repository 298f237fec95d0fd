#!/usr/bin/env bash
# Results v5 (docs/RESULTS.md): results v4's recipe (gpu_results_v4.sh: 8 tasks x 25 demos with rvt2's own
# insert_peg expert, refinements merged, batch 192, 1,200 steps, 50 seeds per task, held-out insertion
# demos) with 1-degree rotation bins trained against 2-degree Gaussian targets and decoded between bin
# centres: `rvt2 train --rotation-bins 360 --rotation-sigma 2`.
#
# Same steps as gpu_results_v4.sh: `stash` (each .gpu/site.part.* piece but the last), `start` (the last
# piece and .gl), `evaluate`; or `all` on a one-GPU workstation with rvt2 and its simulator installed.
set -euo pipefail
export RUN=${RUN:-v5} ROTATION=${ROTATION:---rotation-bins 360 --rotation-sigma 2}
exec bash "$(dirname "$0")/gpu_results_v4.sh" "$@"
