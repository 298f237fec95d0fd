"""Can the cameras see the goal when the policy must decide where to carry the object?

RVT-2 predicts each keyframe from the current observation alone. On a task whose goal is a marker the
policy must see (tasks/*.toml `show_hidden`, e.g. pick_cube's green sphere), the last keyframe, which
carries the object to the goal, is predicted from the observation at the keyframe before it. This runs
the scripted expert on each seed, finds its keyframes as `rvt2 extract-keyframes` would, restores the
scene at that keyframe (`--after-close` control steps later where the gripper closes there, once the
fingers hold the object), renders the task's cameras with segmentation
(`rvt2cli.record.scene.capture_cameras`) and counts the marker's pixels in each. Evaluation journals
(`rvt2 eval`'s episodes.jsonl) mark which seeds their policy failed, so visibility can be compared between
failed and successful episodes. `--expert` measures another expert on the same scenes (ManiSkill's
pick-cube expert carries from the grasp: `mani_skill.examples.motionplanning.panda.solutions:solvePickCube`).

    python -m benchmarks.goal_visibility [--task pick_cube] [--seeds 50] [--first-seed 10000] [--expert SPEC]
                                         [--after-close 8] [--journal NAME=episodes.jsonl ...] [--json out.json]
"""

import argparse
import json
from pathlib import Path

import numpy as np

from benchmarks.machine import describe
from rvt2cli.errors import UserError
from rvt2cli.tasks import get_task


def marker_ids(env, names) -> list[int]:
    """Segmentation ids of the scene actors with these names."""
    from mani_skill.utils.structs import Actor

    return [i for i, obj in env.unwrapped.segmentation_id_map.items() if isinstance(obj, Actor) and obj.name in names]


def visibility(env, task, seed: int, after_close: int, expert: str | None = None) -> tuple[dict[str, int], str]:
    """The marker's pixels per camera where the carry is decided: at the keyframe before the last
    (`after_close` control steps later if the gripper closes there), and how the expert's run ended
    (success, failed, ...). `expert` replaces the task's."""
    from dataclasses import replace

    from rvt2cli.eval.sources import expert_keyframes
    from rvt2cli.record.scene import capture_cameras, restore_sim_state

    run, keyframes = expert_keyframes(env, replace(task, expert=expert or task.expert), seed)
    if len(keyframes) < 2 or keyframes[-2].gripper_open:
        raise SystemExit(f"{task.name} seed {seed}: the expert holds nothing before its last keyframe; "
                         "choose a task that carries a grasped object to its goal")
    decision = keyframes[-2]
    frame = decision.frame + (after_close if "gripper" in decision.reasons else 0)
    restore_sim_state(env, run.frames[min(frame, len(run.frames) - 1)].sim)
    segmentation: dict = {}
    capture_cameras(env, segmentation)
    ids = marker_ids(env, set(task.show_hidden))
    return {camera: int(np.isin(seg, ids).sum()) for camera, seg in segmentation.items()}, run.status


def failed_seeds(path: str, task: str) -> set[int]:
    """The seeds of `task` whose policy episode failed in an evaluation journal."""
    from rvt2cli.eval.journal import read_journal

    _, records = read_journal(Path(path))
    return {r["seed"] for r in records if r["task"] == task and r["source"] == "policy" and not r["success"]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="pick_cube")
    p.add_argument("--seeds", type=int, default=50)
    p.add_argument("--first-seed", type=int, default=10_000)
    p.add_argument("--expert", help="another expert than the task's (module:function), on the same scenes")
    p.add_argument("--after-close", type=int, default=8,
                   help="where the carry is decided at a closing gripper: this many control steps later")
    p.add_argument("--journal", action="append", default=[], metavar="NAME=PATH",
                   help="an evaluation's episodes.jsonl: which seeds its policy failed (repeatable)")
    p.add_argument("--json", help="write the rows and the summary here too")
    args = p.parse_args(argv)
    task = get_task(args.task)
    if not task.show_hidden:
        raise SystemExit(f"{task.name}: tasks/{task.name}.toml shows no hidden marker (show_hidden); choose a task that does")
    journals = dict(j.split("=", 1) for j in args.journal)
    try:
        failed = {name: failed_seeds(path, task.name) for name, path in journals.items()}
    except (OSError, UserError) as error:
        raise SystemExit(str(error)) from None

    from rvt2cli.record.scene import make_env

    env = make_env(task)
    rows = []
    expert = args.expert or task.expert
    print(f"{task.name}: pixels of {', '.join(task.show_hidden)} per camera where {expert} decides the carry; {describe()}")
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        pixels, status = visibility(env, task, seed, args.after_close, expert)
        row = {"seed": seed, "expert": status, "pixels": pixels, "total": sum(pixels.values()),
               "failed": {name: seed in seeds for name, seeds in failed.items()}}
        rows.append(row)
        marks = " ".join(f"{name}:{'FAIL' if bad else 'ok'}" for name, bad in row["failed"].items())
        ended = "" if status == "success" else f"  (the expert's run: {status})"
        print(f"seed {seed}: {row['total']:5d} px  {pixels}  {marks}{ended}", flush=True)
    summary = {}
    for name in failed:
        groups = {kind: [r["total"] for r in rows if r["failed"][name] == (kind == "failed")] for kind in ("failed", "succeeded")}
        summary[name] = {kind: {"episodes": len(v), "median_px": float(np.median(v)) if v else None,
                                "none_visible": sum(t == 0 for t in v)} for kind, v in groups.items()}
        print(f"{name}: " + "; ".join(f"{kind} {s['episodes']}, median {s['median_px']} px, {s['none_visible']} with none"
                                      for kind, s in summary[name].items()))
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": describe(), "task": task.name, "expert": expert,
                                               "after_close": args.after_close,
                                               "rows": rows, "summary": summary}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
