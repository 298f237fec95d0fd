"""Where a closed-loop evaluation's time goes, without the model: `rvt2 eval --replay` of recorded runs.

    python -m benchmarks.eval_bench JOURNAL... [--tasks a,b] [--episodes 2] [--seed 10000] [--json out.json]

JOURNALs are `episodes.jsonl` files (plain, .gz or .xz) of policy evaluations. Their predicted keyframes run
again through `evaluate` (what `rvt2 eval` runs: the scene, the cameras, the cloud, the executor and
its planner), in one process, for the first --episodes seeds from --seed of each task they hold. A
policy on a GPU adds its prediction to each keyframe; on a GPU machine the rest is what the CPU cores
pay for, so it sets how many episodes a minute a machine's cores evaluate. Prints seconds per episode and
per keyframe, by task, and the share of the time in each part of an episode (`benchmarks.profile_parts`).
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

from benchmarks.machine import describe
from benchmarks.profile_parts import PartTimer
from rvt2cli.eval.journal import Journal, read_journal
from rvt2cli.eval.options import EvalOptions
from rvt2cli.eval.runner import evaluate

# The parts of an episode: the functions that do them, where `evaluate` looks them up.
PARTS = {
    "render the cameras": [("rvt2cli.eval.rollout", "capture_cameras")],
    "fuse the clouds": [("rvt2cli.eval.rollout", "fuse")],
    "clear the planner's cloud near the robot": [("rvt2cli.eval.executor", "Executor.clear_cloud")],
    "give the planner its cloud": [("mplib.planner", "Planner.update_point_cloud")],
    "plan (screw, RRT, timing)": [("mplib.planner", "Planner.plan_screw"), ("mplib.planner", "Planner.plan_qpos_to_pose")],
    "simulate (control steps)": [("rvt2cli.eval.executor", "Executor._step")],
    "reset the scene": [("mani_skill.envs.sapien_env", "BaseEnv.reset")],
}


def merged_journal(paths: list[Path], folder: Path) -> Path:
    """One journal in `folder` of every policy episode of `paths` (plain, .gz or .xz), with the first one's plan."""
    journal = None
    for path in paths:
        plan, records = read_journal(path)
        journal = journal or Journal(folder, plan, resume=False)
        for record in records:
            if record["source"] == "policy":
                journal.append(record)
    return journal.path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("journals", nargs="+", type=Path)
    parser.add_argument("--tasks", default="", help="comma-separated (default: every task the journals hold)")
    parser.add_argument("--episodes", type=int, default=2, help="per task")
    parser.add_argument("--seed", type=int, default=10_000)
    parser.add_argument("--json")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as work:
        journal = merged_journal(args.journals, Path(work))
        opts = EvalOptions(checkpoint=None, replay=str(journal), tasks=tuple(t for t in args.tasks.split(",") if t),
                           episodes=args.episodes, seed=args.seed, out=str(Path(work) / "eval"))
        episodes, last = [], [time.perf_counter()]

        def timed(job, outcome, finished) -> None:
            now = time.perf_counter()
            episodes.append({"task": job.task, "seed": job.seed, "success": outcome.success, "keyframes": len(outcome.steps),
                             "control_steps": outcome.control_steps, "seconds": now - last[0]})
            last[0] = now

        start = time.perf_counter()
        with PartTimer(PARTS) as timer:
            evaluate(opts, on_outcome=timed, on_start=lambda n: last.__setitem__(0, time.perf_counter()))
        total = time.perf_counter() - start
    parts = timer.seconds
    spent = sum(e["seconds"] for e in episodes)
    print(f"{len(episodes)} episodes in {spent:.1f} s ({total:.1f} s with start-up), one process")
    print("| task | episodes | successes | s per episode | s per keyframe |")
    print("|---|---|---|---|---|")
    for task in sorted({e["task"] for e in episodes}):
        mine = [e for e in episodes if e["task"] == task]
        seconds, keyframes = sum(e["seconds"] for e in mine), sum(e["keyframes"] for e in mine)
        print(f"| {task} | {len(mine)} | {sum(e['success'] for e in mine)} | {seconds / len(mine):.1f} | "
              f"{seconds / max(1, keyframes):.2f} |")
    print("\n| part of an episode | s | share |")
    print("|---|---|---|")
    for name, seconds in parts.items():
        print(f"| {name} | {seconds:.1f} | {seconds / spent:.0%} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": describe(), "journals": [str(p) for p in args.journals],
                                               "seconds": spent, "parts_s": parts, "episodes": episodes}, indent=2))


if __name__ == "__main__":
    main()
