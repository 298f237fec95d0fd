"""Expert success and the spread of its aligned and inserted TCP in the face's frame, from v6.jsonl and
fixed_offsets.jsonl: `python benchmarks/results/v7_h200/expert_aligned_spread/summary.py`."""
import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
for tag in ("v6", "fixed_offsets"):
    rows = [json.loads(line) for line in (HERE / f"{tag}.jsonl").read_text().splitlines()]
    complete = [r for r in rows if r["n"] == 7]
    print(f"{tag}: expert {sum(r['ok'] for r in rows)}/{len(rows)}")
    for name, index in (("aligned (last refinement)", 5), ("insertion", 6)):
        x = np.array([r["kf"][index][0][0] for r in complete])
        print(f"  {name}: TCP at x = {x.mean():.1f} mm in the face frame on average (negative: before the face), std {x.std():.1f}, range {x.min():.0f}..{x.max():.0f}")
