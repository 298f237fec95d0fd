"""Recording benchmarks: expert success per task (and per variation), and episodes per minute and MB per episode.

    python -m benchmarks.record_bench [--tasks a,b | --task-set rlbench18] [--seeds 20] [--first-seed 0]
                                      [--episodes 8] [--workers 2] [--json out.json] [--quick]
    python -m benchmarks.record_bench --task-set rlbench18 --profile 2 [--json out.json]

Expert success runs each task's expert on seeds FIRST..FIRST+N-1 without rendering, each seed in the
variation `rvt2 record` gives it (`--first-seed 10000`: the seeds `rvt2 eval` uses; `--episodes 0` skips
the throughput part). Throughput records successful episodes with the default camera rig, as
`rvt2 record` does: of insert_peg, or with --task-set of every task of the set (the time for all).
`--profile N` records N demos of each task in one process, with `rvt2 record`'s own function, and
prints where a demo's core-seconds go (planning, physics, scene builds, state restores,
camera captures, keyframes, MCAP writing).
"""

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from benchmarks.machine import describe
from benchmarks.profile_parts import PartTimer
from rvt2cli.record.expert import run_expert
from rvt2cli.record.recorder import RecordOptions, record_episode, record_tasks
from rvt2cli.record.scene import make_env
from rvt2cli.tasks import all_tasks, episode_variation, tasks_of_set


def expert_success(task, seeds: int, first_seed: int = 0) -> dict:
    env = make_env(task, cameras=("front",), image_size=32)
    statuses, variations, frames, start = [], [], [], time.perf_counter()
    for seed in range(first_seed, first_seed + seeds):
        variation = episode_variation(seed, task.variation_choices())
        run = run_expert(env, task.expert, seed, max_frames=task.max_steps, variation=variation)
        statuses.append(run.status)
        variations.append(variation)
        frames.append(len(run.frames))
    env.close()
    per_variation = {str(v): sum(s == "success" for s, w in zip(statuses, variations) if w == v) / variations.count(v)
                     for v in sorted(set(variations))}
    return {"task": task.name, "seeds": seeds, "first_seed": first_seed, "success": statuses.count("success") / seeds,
            "per_seed": statuses, "variations": variations, "per_variation": per_variation,
            "statuses": {s: statuses.count(s) for s in sorted(set(statuses))},
            "mean_frames": sum(frames) / seeds, "seconds_per_episode": (time.perf_counter() - start) / seeds}


def record_throughput(episodes: int, workers: int, tasks=("insert_peg",)) -> dict:
    """`rvt2 record`'s own function over all the tasks at once, as `rvt2 record --task-set` runs it.
    A line as each task completes, so that a run stopped early still tells how far it came."""
    start = time.perf_counter()

    def on_result(result, summary):
        if result.success and len(summary.successes) == summary.requested:
            print(f"{time.perf_counter() - start:.0f} s: {summary.task} done ({episodes} demos, "
                  f"{len(summary.results)} attempts)", flush=True)

    with tempfile.TemporaryDirectory() as out:
        summaries = record_tasks(list(tasks), episodes, out, seed=0, workers=workers, options=RecordOptions(),
                                 on_result=on_result)
        seconds = time.perf_counter() - start
    sizes = [r.size_bytes for s in summaries for r in s.successes]
    return {"tasks": list(tasks), "episodes": len(sizes), "attempts": sum(len(s.results) for s in summaries),
            "workers": workers, "seconds": seconds, "episodes_per_minute": 60 * len(sizes) / seconds,
            "mb_per_episode": sum(sizes) / len(sizes) / 1e6, "max_mb": max(sizes) / 1e6,
            "per_task": {s.task: {"episodes": len(s.successes), "attempts": len(s.results), "done_after_s": s.seconds}
                         for s in summaries}}


# The steps of recording one demo: the functions that do them, where rvt2 record looks them up.
RECORD_PARTS = {
    "reset the scene (rebuild it)": [("mani_skill.envs.sapien_env", "BaseEnv.reset")],
    "build the expert's planner": [("mani_skill.examples.motionplanning.panda.motionplanner", "PandaArmMotionPlanningSolver.__init__")],
    "plan the expert's motions (mplib)": [("mplib.planner", "Planner.plan_screw"), ("mplib.planner", "Planner.plan_qpos_to_pose"),
                                          ("mplib.planner", "Planner.plan_qpos_to_qpos")],
    "simulate (control steps)": [("mani_skill.envs.sapien_env", "BaseEnv.step")],
    "read each frame (joints, contacts, simulator state)": [("rvt2cli.record.expert", "RecordingWrapper._record")],
    "find the keyframes": [("rvt2cli.record.recorder", "find_keyframes")],
    "restore the observed frames' states": [("rvt2cli.record.recorder", "restore_sim_state")],
    "capture the cameras": [("rvt2cli.record.recorder", "capture_cameras")],
    "write the MCAP file (encode, compress)": [("rvt2cli.data.writer", "EpisodeWriter.write_instruction"),
                                               ("rvt2cli.data.writer", "EpisodeWriter.write_frame"),
                                               ("rvt2cli.data.writer", "EpisodeWriter.write_observation"),
                                               ("rvt2cli.data.writer", "EpisodeWriter.finish")],
}


def record_profile(names, demos: int) -> dict:
    """`demos` successful demos of each task, recorded one after another in this process by `rvt2 record`'s
    own `record_episode`, each step timed (`RECORD_PARTS`)."""
    results, timer = [], PartTimer(RECORD_PARTS)
    with tempfile.TemporaryDirectory() as out:
        for name in names:
            task = all_tasks()[name]
            env = make_env(task)
            successes, seed = 0, 0
            while successes < demos and seed < 10 * demos + 10:
                start = time.perf_counter()
                with timer:   # the episode's steps only, not the scene's first build in make_env
                    result = record_episode(env, task, seed, Path(out), RecordOptions())
                results.append({"task": name, "seed": seed, "status": result.status, "frames": result.frames,
                                "seconds": time.perf_counter() - start})
                successes += result.success
                seed += 1
            env.close()
    return {"tasks": list(names), "demos": sum(r["status"] == "success" for r in results), "attempts": len(results),
            "seconds": sum(r["seconds"] for r in results), "captures": timer.calls["capture the cameras"],
            "capture_path": os.environ.get("RVT2_CAPTURE", "auto"), "parts_s": timer.seconds, "part_calls": timer.calls,
            "episodes": results}


def print_profile(p: dict) -> None:
    demos = max(1, p["demos"])
    print(f"\n{p['demos']} demos ({p['attempts']} attempts) of {len(p['tasks'])} tasks in {p['seconds']:.1f} s, one process "
          f"(capture path {p['capture_path']}): {p['seconds'] / demos:.2f} s per demo, {p['captures']} camera captures "
          f"({p['captures'] / demos:.1f} per demo)")
    print("| step of recording a demo | s | share | s per demo |\n|---|---|---|---|")
    for name, seconds in p["parts_s"].items():
        print(f"| {name} | {seconds:.1f} | {seconds / p['seconds']:.0%} | {seconds / demos:.3f} |")
    rest = p["seconds"] - sum(p["parts_s"].values())
    print(f"| the rest (expert logic, checks) | {rest:.1f} | {rest / p['seconds']:.0%} | {rest / demos:.3f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--tasks", help="comma-separated (default: all)")
    parser.add_argument("--task-set", help="the tasks of this named set (e.g. rlbench18), also for the throughput")
    parser.add_argument("--json", help="write results here")
    parser.add_argument("--profile", type=int, default=0, metavar="N",
                        help="record N demos of each task in one process: where a demo's time goes")
    parser.add_argument("--quick", action="store_true", help="2 seeds of 2 tasks, 1 episode: checks that it runs")
    args = parser.parse_args()
    names = args.tasks.split(",") if args.tasks else tasks_of_set(args.task_set) if args.task_set else list(all_tasks())
    if args.profile:
        results = {"machine": describe(), "profile": record_profile(names, args.profile)}
        print_profile(results["profile"])
        if args.json:
            with open(args.json, "w") as f:
                json.dump(results, f, indent=2)
        return
    seeds, episodes = args.seeds, args.episodes
    if args.quick:
        names, seeds, episodes = ["push_cube", "insert_peg"], 2, 1
    results = {"machine": describe(), "expert": [], "throughput": None}
    if seeds:
        print("| task | expert success | per variation | seeds | mean frames | s/episode (no rendering) |\n|---|---|---|---|---|---|")
    for name in names if seeds else []:
        r = expert_success(all_tasks()[name], seeds, args.first_seed)
        results["expert"].append(r)
        spread = " ".join(f"{v}:{rate:.2f}" for v, rate in r["per_variation"].items())
        print(f"| {name} | {r['success']:.2f} | {spread} | {seeds} | {r['mean_frames']:.0f} | {r['seconds_per_episode']:.2f} |",
              flush=True)
    if episodes:
        t = record_throughput(episodes, args.workers, names if args.task_set else ("insert_peg",))
        results["throughput"] = t
        print(f"\n{','.join(t['tasks'])} with {t['workers']} workers: {t['episodes_per_minute']:.1f} successful episodes/min "
              f"({t['episodes']} episodes, {t['attempts']} attempts, {t['seconds']:.0f} s), "
              f"{t['mb_per_episode']:.2f} MB/episode (max {t['max_mb']:.2f})")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
