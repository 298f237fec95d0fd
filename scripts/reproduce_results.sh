#!/usr/bin/env bash
# A published experiment of docs/RESULTS.md on a GPU workstation with rvt2 installed (`make setup`,
# `source .venv/bin/activate`): every phase of experiments/NAME.toml (record, held-out demos, train, eval,
# offline score, oracle), each timed into data/experiments/NAME/phases.tsv.
#
#   bash scripts/reproduce_results.sh rvt2_25demos                        # every phase, one GPU
#   bash scripts/reproduce_results.sh rvt2_10demos --gpus 2               # training on two GPUs, the global batch kept
#   bash scripts/reproduce_results.sh rvt2_25demos --phase train,eval     # some phases
#   bash scripts/reproduce_results.sh rvt2_25demos --print                # only print the commands
#
# Any option of `python -m benchmarks.experiment` may follow the name (--workers, --out, --training-seeds, ...).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ $# -lt 1 ]; then
  echo "usage: $0 EXPERIMENT [options of python -m benchmarks.experiment]; experiments: $(ls experiments | sed 's/\.toml$//' | tr '\n' ' ')" >&2
  exit 2
fi
name=$1
shift
PYTHON=${PYTHON:-$(command -v python || echo .venv/bin/python)}
mode=--run
for arg in "$@"; do [ "$arg" = --print ] && mode=; done
exec "$PYTHON" -m benchmarks.experiment "$name" $mode "$@"
