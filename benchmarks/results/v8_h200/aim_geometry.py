"""How far stage 2's centre lies from insert_peg's hole mouth for each candidate aim offset, at the
aligned pose before the insertion and at the insertion itself (the raw measurement behind
tasks/insert_peg.toml's aim_offset and docs/RESULTS.md v8).

    python benchmarks/results/v8_h200/aim_geometry.py DEMOS_DIR...   # annotated insert_peg demos

The mouth is the goal pose's position (where the peg's centre sits when inserted: the box's face).
"In view" is within stage 2's +-10 cm box; "with the TCP" also keeps the TCP 1 cm inside it.
"""

import sys
from pathlib import Path

import numpy as np

from rvt2cli.data.reader import read_episode
from rvt2cli.model.observation import aimed_target
from rvt2cli.record.scene import make_env
from rvt2cli.tasks import get_task

OFFSETS = (0.0, 0.06, 0.08, 0.10, 0.12, 0.15)
env = make_env(get_task("insert_peg"), cameras=("front",), image_size=32)
rows = []
for path in sorted(p for d in sys.argv[1:] for p in Path(d).glob("insert_peg_*.mcap")):
    ep = read_episode(path)
    env.reset(seed=ep.meta.seed)
    mouth = env.unwrapped.goal_pose.p[0].cpu().numpy()
    keyframes = ep.require_keyframes().keyframes
    for name, k in (("aligned", keyframes[-2]), ("insertion", keyframes[-1])):
        for offset in OFFSETS:
            centre = aimed_target(k.position, k.quaternion, [offset, 0, 0])[0]
            rows.append((name, offset, np.abs(centre - mouth).max(), np.abs(centre - np.asarray(k.position)).max()))
print("| keyframe | aim offset (m) | mouth in view | mouth and TCP in view | median distance to the mouth (mm, max-norm) |")
print("|---|---|---|---|---|")
for name in ("aligned", "insertion"):
    for offset in OFFSETS:
        r = [x for x in rows if x[0] == name and x[1] == offset]
        print(f"| {name} | {offset:.2f} | {np.mean([x[2] <= 0.1 for x in r]):.0%} | "
              f"{np.mean([x[2] <= 0.09 and x[3] <= 0.09 for x in r]):.0%} | {np.median([x[2] for x in r]) * 1000:.0f} (n={len(r)}) |")
