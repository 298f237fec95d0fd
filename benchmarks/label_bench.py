"""Do collision flags mean the same thing in every demo? The scripted expert's keyframes on N seeds per
task, labelled as `rvt2 extract-keyframes` labels them: by contacts alone (the rule before v3) and by
contacts or arrival within 5 mm (v3). Per task: how many demos label their grasp and their final
keyframe (the insertion, the placement) collision-ignoring, and the demos' keyframe counts.

    python -m benchmarks.label_bench [--tasks insert_peg,plug_charger] [--seeds 20] [--first-seed 0]
                                     [--merge-refinements MM] [--json out.json] [--quick]

The expert runs without rendering (the code `rvt2 record` runs); only successful demos count, as
`rvt2 record` keeps only those.
"""

import argparse
import json

import numpy as np

from benchmarks.machine import describe
from rvt2cli.keyframes.extract import label_keyframes
from rvt2cli.keyframes.rule import KeyframeParams
from rvt2cli.record.expert import run_expert
from rvt2cli.record.scene import make_env
from rvt2cli.robot import RobotFacts
from rvt2cli.tasks import get_task


def label_demo(env, task, seed: int, params: KeyframeParams):
    """(keyframes by contacts alone, keyframes by rule v3), or None if the expert failed this seed."""
    run = run_expert(env, task.expert, seed, max_frames=task.max_steps)
    if run.status != "success":
        return None
    frames = run.frames
    facts = RobotFacts.from_agent(env.unwrapped.agent)
    args = ([f.gripper_command for f in frames],
            facts.arm(np.array([f.state["joint_velocities"] for f in frames]), frames[0].state["joint_names"]),
            [f.contacts for f in frames], [f.state["tcp_pose"] for f in frames], params)
    return label_keyframes(*args), label_keyframes(*args, near=[f.near for f in frames])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="insert_peg,plug_charger")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--merge-refinements", type=float, default=0.0, metavar="MM")
    parser.add_argument("--json")
    parser.add_argument("--quick", action="store_true", help="two seeds of one task: checks that it runs")
    args = parser.parse_args()
    tasks, seeds = args.tasks.split(","), args.seeds
    if args.quick:
        tasks, seeds = tasks[:1], 2
    params = KeyframeParams(merge_m=args.merge_refinements / 1000)
    rows = []
    print("| task | demos | grasp ignores collisions: contacts / v3 | final keyframe ignores collisions: contacts / v3 "
          "| keyframes per demo |\n|---|---|---|---|---|")
    for name in tasks:
        task = get_task(name)
        env = make_env(task, cameras=("front",), image_size=32)
        labelled = [d for d in (label_demo(env, task, seed, params) for seed in range(args.first_seed, args.first_seed + seeds)) if d]
        env.close()
        n = len(labelled)

        def count(which: int, pick) -> int:
            return sum(bool(pick(demo[which]) and pick(demo[which]).ignore_collisions) for demo in labelled)

        def grasp(kfs):
            return next((k for k in kfs if "gripper" in k.reasons), None)

        def final(kfs):
            return kfs[-1] if kfs else None

        row = {"task": name, "demos": n, "grasp_contacts": count(0, grasp), "grasp_v3": count(1, grasp),
               "final_contacts": count(0, final), "final_v3": count(1, final),
               "keyframes_per_demo": float(np.mean([len(d[1]) for d in labelled])) if n else 0.0}
        rows.append(row)
        print(f"| {name} | {n} | {row['grasp_contacts']}/{n} / {row['grasp_v3']}/{n} | {row['final_contacts']}/{n} / "
              f"{row['final_v3']}/{n} | {row['keyframes_per_demo']:.1f} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": describe(), "seeds": seeds, "first_seed": args.first_seed,
                       "merge_refinements_mm": args.merge_refinements, "rows": rows}, f, indent=2)


if __name__ == "__main__":
    main()
