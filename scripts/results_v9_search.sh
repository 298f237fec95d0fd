#!/usr/bin/env bash
# docs/RESULTS.md v9, the insertion search, on any machine with rvt2 installed (`make setup`); no GPU.
# It replays the keyframes that results v8's policies predicted on an H200 (their journals are in
# benchmarks/results/v8_h200/) through today's executor, with the search (`rvt2 eval --replay`), runs
# the oracle on 50 seeds, and the precision budget with and without the search.
#
#   bash scripts/results_v9_search.sh                     # everything (38 minutes on 2 cores)
#   bash scripts/results_v9_search.sh replay stops        # some phases, in this order (stops reads replay's)
#
# Settings (environment): OUT (default data/results_v9; data/ is git-ignored), WORKERS (simulator
# processes, default: the number of cores), BUDGET_SEEDS (precision budget seeds per variant, 16), RVT2.
# Without the search, a replay gives the recorded outcome (tests/test_search.py checks it on two seeds),
# so the v8 journals themselves are the "without" column.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-data/results_v9}
WORKERS=${WORKERS:-$(nproc)}
BUDGET_SEEDS=${BUDGET_SEEDS:-16}
RVT2=${RVT2:-rvt2}
V8=benchmarks/results/v8_h200
if ! command -v "$RVT2" > /dev/null; then
  echo "$RVT2: not found; run \`make setup\` and \`source .venv/bin/activate\` (or set RVT2)" >&2
  exit 2
fi
mkdir -p "$OUT"
export HF_HUB_OFFLINE=1

phase() {  # name, command...: run and time one phase into $OUT/phases.tsv
  local name=$1 start
  shift
  start=$(date +%s)
  echo "== $name: $*"
  "$@"
  printf '%s\t%s\n' "$name" "$(( $(date +%s) - start ))" >> "$OUT/phases.tsv"
}

replay() {  # journal, out, tasks, episodes
  "$RVT2" eval --replay "$1" --out "$OUT/$2" --tasks "$3" --episodes "$4" --workers "$WORKERS" --no-progress
}

run_replay() {
  phase replay_peg_only replay "$V8/insert_peg_only/eval_v8_peg/episodes.jsonl" replay_peg_only insert_peg 50
  phase replay_eight_tasks replay "$V8/eight_tasks/eval_v8/episodes.jsonl" replay_eight_tasks insert_peg,plug_charger 50
  phase replay_proxy replay "$V8/proxy_2task/eval_v8_proxy/episodes.jsonl" replay_proxy insert_peg,plug_charger 30
  phase replay_ten_demos replay "$V8/eight_tasks/eval_v8_10/episodes.jsonl" replay_ten_demos insert_peg,plug_charger 25
}

run_oracle() {
  phase oracle "$RVT2" eval --oracle --tasks insert_peg,plug_charger --episodes 50 --seed 10000 --workers "$WORKERS" \
    --out "$OUT/oracle" --no-progress
}

run_stops() {  # where the first insertion leaves the peg pushed straight, against the replays above
  phase stops_peg_only python -m benchmarks.insertion_stops "$V8/insert_peg_only/eval_v8_peg/episodes.jsonl" \
    --searched "$OUT/replay_peg_only" --workers "$WORKERS" --json "$OUT/insertion_stops_peg_only.json"
  phase stops_eight_tasks python -m benchmarks.insertion_stops "$V8/eight_tasks/eval_v8/episodes.jsonl" \
    --searched "$OUT/replay_eight_tasks" --workers "$WORKERS" --json "$OUT/insertion_stops_eight_tasks.json"
}

run_budget() {
  for search in on off; do
    local flag=()
    [[ $search == off ]] && flag=(--no-insertion-search)
    phase "budget_$search" python -m benchmarks.precision_budget --tasks insert_peg --variants pos4,turn1 \
      --seeds "$BUDGET_SEEDS" --workers "$WORKERS" --json "$OUT/precision_budget_$search.json" "${flag[@]}"
  done
}

phases=("$@")
(( ${#phases[@]} )) || phases=(replay stops oracle budget)
for p in "${phases[@]}"; do
  case $p in
    replay|stops|oracle|budget) "run_$p" ;;
    *) echo "unknown phase '$p' (replay, stops, oracle, budget)" >&2; exit 2 ;;
  esac
done
