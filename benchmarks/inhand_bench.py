"""Why open-loop replay cannot match the expert on insertion tasks: the object's pose in the hand.

    python -m benchmarks.inhand_bench [--tasks insert_peg,plug_charger] [--seeds 25] [--json out.json]

For each seed, the scripted expert runs (its keyframes are the oracle's), then the oracle replays the
keyframes with `rvt2 eval`'s executor. At every keyframe after the grasp this compares the held
object's pose relative to the TCP in the two runs. The expert computes its insertion poses from the
object's true pose in its own hand; the oracle replays those TCP poses with the object wherever its own
grasp put it. Where the two grasps differ by more than the clearance (PegInsertionSide: 3 mm radial;
PlugCharger: 0.5 mm per side), the replay cannot insert, however precise the executor.
"""

import argparse
import json

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks.machine import describe
from rvt2cli.eval import rollout
from rvt2cli.eval.sources import OracleSource
from rvt2cli.record.expert import run_expert
from rvt2cli.record.scene import make_env, restore_sim_state, tcp_pose
from rvt2cli.tasks import get_task

HELD = {"insert_peg": "peg", "plug_charger": "charger", "lift_peg_upright": "peg"}
CLEARANCE_MM = {"insert_peg": 3.0, "plug_charger": 0.5}


def in_hand(env, name: str) -> tuple[np.ndarray, Rotation]:
    """The object's pose in the TCP frame: (position [3] m, rotation)."""
    tcp = tcp_pose(env).astype(np.float64)
    raw = getattr(env.unwrapped, name).pose.raw_pose[0].cpu().numpy().astype(np.float64)
    turn = Rotation.from_quat(tcp[3:])
    return turn.inv().apply(raw[:3] - tcp[:3]), turn.inv() * Rotation.from_quat(raw[[4, 5, 6, 3]])


def seed_row(env, task, seed: int, oracle: OracleSource) -> dict:
    name = HELD[task.name]
    run = run_expert(env, task.expert, seed, task.max_steps)
    keyframes = oracle.keyframes(task, seed)
    expert = []
    for k in keyframes:
        restore_sim_state(env, run.frames[k.frame].sim)
        expert.append(in_hand(env, name))
    replayed = []
    execute = rollout.Executor.execute

    def observed(self, target, scene_points=None):
        reach = execute(self, target, scene_points)
        replayed.append(in_hand(self.env, name))
        return reach

    rollout.Executor.execute = observed
    try:
        outcome = rollout.run_episode(env, task, seed, oracle, task.instruction(seed)[0])
    finally:
        rollout.Executor.execute = execute
    grasp = next((i for i, k in enumerate(keyframes) if not k.gripper_open), len(keyframes))
    diffs = [(float(np.linalg.norm(e[0] - r[0]) * 1000), float(np.degrees((e[1].inv() * r[1]).magnitude())))
             for e, r in list(zip(expert, replayed))[grasp + 1:-1]]   # carrying, before the final insertion
    return {"seed": seed, "expert": run.status == "success", "oracle": outcome.success,
            "in_hand_mm": max((d[0] for d in diffs), default=None), "in_hand_deg": max((d[1] for d in diffs), default=None)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="insert_peg,plug_charger")
    parser.add_argument("--seeds", type=int, default=25)
    parser.add_argument("--first-seed", type=int, default=10_000)
    parser.add_argument("--json")
    args = parser.parse_args()
    results = {"machine": describe(), "tasks": {}}
    print("| task | seeds the expert solved | oracle solved of those | in-hand difference mm, oracle solved (median) | "
          "oracle failed (median) | clearance mm |\n|---|---|---|---|---|---|")
    for name in args.tasks.split(","):
        task = get_task(name)
        env = make_env(task, cameras=("front",), image_size=32)
        oracle = OracleSource(env)
        rows = [seed_row(env, task, s, oracle) for s in range(args.first_seed, args.first_seed + args.seeds)]
        env.close()
        results["tasks"][name] = rows
        solved = [r for r in rows if r["expert"] and r["in_hand_mm"] is not None]
        ok = [r["in_hand_mm"] for r in solved if r["oracle"]]
        bad = [r["in_hand_mm"] for r in solved if not r["oracle"]]
        median = lambda v: f"{np.median(v):.2f} (n={len(v)})" if v else "-"  # noqa: E731
        print(f"| {name} | {len(solved)} | {len(ok)} | {median(ok)} | {median(bad)} | {CLEARANCE_MM.get(name, '-')} |", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
