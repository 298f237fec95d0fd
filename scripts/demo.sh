#!/usr/bin/env bash
# `make demo`: the whole rvt2 pipeline at small scale on this machine's CPU (about 10 minutes on 2 cores):
# record demos in the simulator -> keyframes -> the network's views -> train the small config ->
# closed-loop evaluation next to the oracle -> an ONNX export.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${DEMO_OUT:-out/demo}
RVT2=".venv/bin/rvt2"
rm -rf "$OUT"
mkdir -p "$OUT"
say() { printf '\n== %s\n' "$*"; }

say "1/7 record expert demonstrations (ManiSkill + SAPIEN on the CPU)"
for task in push_cube stack_cube; do
  $RVT2 record --task "$task" --episodes 5 --workers 2 --out "$OUT/demos"
done
say "2/7 keyframes and training samples (record wrote them; the rule again, as after changing its options)"
$RVT2 extract-keyframes "$OUT/demos"
say "3/7 one episode file"
$RVT2 info "$OUT/demos/stack_cube_0000.mcap"
say "4/7 the virtual views the network sees (and the 4x zoom around the next keyframe)"
$RVT2 render "$OUT/demos/stack_cube_0000.mcap" --frame 0 --zoom-at next-keyframe --out "$OUT/views"
say "5/7 train the small config (the paper's network needs a GPU: --config rvt2)"
$RVT2 train --data "$OUT/demos" --out "$OUT/run" --config small --steps 1200 --batch-size 8 --lr 3e-3 \
  --warmup 50 --max-points 20000 --val-every 400 --save-every 600 --no-progress
say "6/7 evaluate closed-loop on unseen seeds, with the oracle (ground-truth keyframes) beside it"
$RVT2 eval --checkpoint "$OUT/run" --episodes 3 --oracle --workers 2 --out "$OUT/eval"
say "7/7 export a deployable ONNX policy (parity-checked against PyTorch)"
$RVT2 export --checkpoint "$OUT/run" --format onnx --out "$OUT/policy" --max-points 20000
say "done"
echo "report:        $OUT/eval/eval.md (and eval.json, eval.png)"
echo "views:         $OUT/views/"
echo "checkpoint:    $OUT/run/last   (train.csv, tb/ for TensorBoard)"
echo "ONNX policy:   $OUT/policy/    (python examples/run_exported_policy.py $OUT/policy)"
cat "$OUT/eval/eval.md"
