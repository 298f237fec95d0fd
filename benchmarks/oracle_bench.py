"""The executor's ceiling: the oracle (the scripted expert's own keyframes, replayed by `rvt2 eval`'s
executor) against the expert itself, on the same unseen seeds, with the executor's precision.

    python -m benchmarks.oracle_bench [--tasks a,b | --task-set rlbench18] [--seeds 25] [--first-seed 10000]
                                      [--workers 2] [--out DIR [--resume]] [--experts record_bench.json ...]
                                      [--json out.json] [--quick]

Per task: oracle success (Wilson interval), expert success on the same seeds, each seed in the same
variation (the seeds spread evenly over a task's variations), success per variation, their agreement (the
fraction of seeds with the same outcome), and the TCP's error at rest over every keyframe the
executor reached (median, p95). The oracle part is exactly `rvt2 eval --oracle` (its report lands in
--out; `--resume` continues an interrupted one there, as `rvt2 eval --resume` does); the expert part is
the code `rvt2 record` runs, without rendering (`--experts`: taken from `benchmarks/record_bench.py --json`
files that ran the same seeds, instead of running it again).
"""

import argparse
import json
import tempfile

import numpy as np

from benchmarks.machine import describe
from benchmarks.record_bench import expert_success
from rvt2cli.eval.options import EvalOptions
from rvt2cli.eval.runner import evaluate
from rvt2cli.tasks import all_tasks, tasks_of_set

TASKS = ("insert_peg", "plug_charger", "lift_peg_upright", "place_sphere", "stack_cube", "pick_cube", "push_cube", "pull_cube")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default=",".join(TASKS))
    parser.add_argument("--task-set", help="the tasks of this named set instead (e.g. rlbench18)")
    parser.add_argument("--seeds", type=int, default=25)
    parser.add_argument("--first-seed", type=int, default=10_000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", help="the oracle's eval report folder (default: a temporary folder)")
    parser.add_argument("--resume", action="store_true", help="continue the oracle evaluation in --out")
    parser.add_argument("--experts", nargs="*", default=[],
                        help="record_bench --json files whose expert runs on the same seeds stand for the expert part")
    parser.add_argument("--json", help="write results here")
    parser.add_argument("--quick", action="store_true", help="one seed of two tasks: checks that it runs")
    args = parser.parse_args()
    tasks, seeds = tasks_of_set(args.task_set) if args.task_set else args.tasks.split(","), args.seeds
    if args.quick:
        tasks, seeds = ["push_cube", "pick_cube"], 1
    out = args.out or tempfile.mkdtemp(prefix="oracle_bench_")
    result = evaluate(EvalOptions(checkpoint=None, tasks=tuple(tasks), episodes=seeds, seed=args.first_seed,
                                  workers=args.workers, oracle=True, out=out, resume=args.resume))
    measured_experts = {(r["task"], r["first_seed"], r["seeds"]): r for path in args.experts
                        for r in json.loads(open(path).read())["expert"]}
    by_seed = {(r["task"], r["seed"]): r["success"] for r in result.report["episodes"]}
    rows = []
    print("| task | oracle success (95% CI) | expert success | oracle / expert | agreement | error at rest mm (median / p95) "
          "| deg (median / p95) | keyframes |\n|---|---|---|---|---|---|---|---|")
    for name in tasks:
        expert = measured_experts.get((name, args.first_seed, seeds)) or expert_success(all_tasks()[name], seeds, args.first_seed)
        expert_ok = [s == "success" for s in expert["per_seed"]]
        oracle_ok = [by_seed[(name, args.first_seed + i)] for i in range(seeds)]
        summary = result.report["tasks"][name]["oracle"]
        pose = summary["pose_error"]
        row = {"task": name, "seeds": seeds, "first_seed": args.first_seed, "oracle": summary["success_rate"],
               "oracle_ci95": summary["ci95"], "expert": float(np.mean(expert_ok)),
               "agreement": float(np.mean([a == b for a, b in zip(oracle_ok, expert_ok)])),
               "oracle_per_seed": oracle_ok, "expert_per_seed": expert["per_seed"], "pose_error": pose,
               "failures": summary["failures"], "replans": summary["replans"],
               "collision_fallbacks": summary["collision_fallbacks"], "variations": expert["variations"],
               "expert_per_variation": expert["per_variation"],
               "oracle_per_variation": {v: r["success_rate"] for v, r in summary["variations"].items()}}
        rows.append(row)
        ratio = row["oracle"] / row["expert"] if row["expert"] else float("nan")
        print(f"| {name} | {row['oracle']:.0%} ({summary['ci95'][0]:.0%}-{summary['ci95'][1]:.0%}) | {row['expert']:.0%} | "
              f"{ratio:.2f} | {row['agreement']:.0%} | {pose['position_mm']['median']:.2f} / {pose['position_mm']['p95']:.2f} | "
              f"{pose['rotation_deg']['median']:.3f} / {pose['rotation_deg']['p95']:.3f} | {pose['keyframes']} |", flush=True)
    for row in rows:
        if len(row["expert_per_variation"]) > 1:
            print(f"{row['task']} per variation (expert / oracle): " + ", ".join(
                f"{v}: {row['expert_per_variation'][v]:.0%} / {row['oracle_per_variation'].get(v, 0):.0%}"
                for v in row["expert_per_variation"]))
    errors = {kind: result.report[key]["oracle"] for kind, key in
              (("all", "pose_error"), ("free", "pose_error_free"), ("contact", "pose_error_contact"))}
    for kind, e in errors.items():
        if not e["keyframes"]:  # e.g. no keyframe made in contact (open_drawer): no error to summarise
            print(f"{kind} oracle keyframes (0)")
            continue
        print(f"{kind} oracle keyframes ({e['keyframes']}): error at rest {e['position_mm']['median']:.2f} mm median, "
              f"{e['position_mm']['p95']:.2f} mm p95; {e['rotation_deg']['median']:.3f} deg median, "
              f"{e['rotation_deg']['p95']:.3f} deg p95")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": describe(), "tasks": rows, "pose_error": errors["all"], "pose_error_free": errors["free"],
                       "pose_error_contact": errors["contact"], "eval_report": out}, f, indent=2)


if __name__ == "__main__":
    main()
