"""Evaluation reports: eval.json, eval.md and a bar chart of success per task (policy vs oracle).

A report is built from episode records (`episode_record`), the same dicts the evaluation journal keeps
one per line as episodes finish, so a report can be rebuilt from the journal of an interrupted run.
Each record carries, per executed keyframe, where the TCP came to rest against its target: the report
gives the median and p95 of those errors per task (the executor's precision) beside the success rates.
"""

import json
import math
from pathlib import Path

import numpy as np

from rvt2cli.atomic import atomic_open
from rvt2cli.errors import UserError
from rvt2cli.eval.rollout import FAILURE_KINDS, Outcome
from rvt2cli.eval.taxonomy import REASONS, closest_gap_mm, count_reasons, failure_reason
from rvt2cli.tasks import get_task

SOURCES = ("policy", "oracle")


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% confidence interval of a success rate (Wilson score interval; sane at 0 and n)."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def episode_record(source: str, outcome: Outcome) -> dict:
    """One finished episode as JSON: its outcome and every keyframe's reach."""
    return {"source": source, "task": outcome.task, "seed": outcome.seed, "success": outcome.success,
            "failure": outcome.failure, "keyframes": outcome.keyframes, "control_steps": outcome.control_steps,
            "step_budget": outcome.step_budget, "task_max_steps": outcome.task_steps,
            "collision_fallbacks": outcome.collision_fallbacks, "unreached_keyframes": sum(not s.reached for s in outcome.steps),
            "replans": outcome.replans, "instruction": outcome.instruction, "variation": outcome.variation,
            "wrong": outcome.wrong, "error": outcome.error, "final_check": outcome.final_check,
            "steps": [{"frame": s.frame, "reached": s.reach.reached, "retry": s.retry, "planner": s.reach.planner,
                       "position_error_mm": s.reach.position_error_mm, "rotation_error_deg": s.reach.rotation_error_deg,
                       "servo_steps": s.reach.servo_steps, "target": list(s.keyframe.pose),
                       "gripper_open": s.keyframe.gripper_open, "ignore_collisions": s.keyframe.ignore_collisions,
                       "why": s.reach.why, "nearest": s.reach.nearest, "start_in_collision": s.reach.start_in_collision,
                       "held": s.held, "gap_mm": s.gap_mm, "probes": s.reach.probes,
                       "search_offset_mm": s.reach.search_offset_mm, "interrupted": s.reach.interrupted}
                      for s in outcome.steps]}


def _percentiles(values: list[float]) -> dict:
    if not values:
        return {"median": None, "p95": None, "max": None}
    a = np.asarray(values)
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(a.max())}


def pose_errors(steps: list[dict]) -> dict:
    """Median, p95 and max of the errors at rest of these executed keyframes (the reached ones, but for
    one the episode's control steps ran out in: that arm is not at rest)."""
    reached = [s for s in steps if s["reached"] and not s.get("interrupted")]
    return {"keyframes": len(reached),
            "position_mm": _percentiles([s["position_error_mm"] for s in reached]),
            "rotation_deg": _percentiles([s["rotation_error_deg"] for s in reached])}


def search_summary(steps: list[dict]) -> dict:
    """The insertion search over these keyframes: how many searched for a hole, found one, and probed."""
    searched = [s for s in steps if s.get("probes")]
    return {"searched": len(searched), "found": sum(s.get("search_offset_mm") is not None for s in searched),
            "probes": sum(s["probes"] for s in searched)}


def summarize(records: list[dict], insertion: bool = False) -> dict:
    n = len(records)
    wins = sum(r["success"] for r in records)
    lo, hi = wilson_interval(wins, n)
    steps = [s for r in records for s in r.get("steps", [])]
    return {
        "episodes": n, "successes": wins, "success_rate": wins / n if n else 0.0, "ci95": [lo, hi],
        "mean_keyframes": sum(r["keyframes"] for r in records) / n if n else 0.0,
        # the successes a budget of the task's own max_steps would have kept (the same episode up to there)
        "successes_within_task_steps": sum(r["success"] and r["control_steps"] <= r.get("task_max_steps", math.inf)
                                           for r in records),
        "failures": {kind: sum(r["failure"] == kind for r in records) for kind in FAILURE_KINDS},
        "reasons": count_reasons(records, insertion),
        "insertion_gap_mm": _percentiles([g for g in (closest_gap_mm(r) for r in records if not r["success"]) if g is not None]),
        "unreached_per_episode": sum(r["unreached_keyframes"] for r in records) / n if n else 0.0,
        "nearest_pose_keyframes": sum(s.get("nearest", False) for r in records for s in r.get("steps", [])),
        "start_in_collision_keyframes": sum(s.get("start_in_collision", False) for r in records for s in r.get("steps", [])),
        "unreached_keyframes": sum(r["unreached_keyframes"] for r in records),
        "replans": sum(r.get("replans", 0) for r in records),
        "collision_fallbacks": sum(r["collision_fallbacks"] for r in records),
        "insertion_search": search_summary(steps),
        "pose_error": pose_errors(steps),
        # keyframes that avoid collisions end in free space, where the executor must land; those that
        # ignore them push into the scene (insertions, pushes) and rest where a contact stops them
        "pose_error_free": pose_errors([s for s in steps if not s["ignore_collisions"]]),
        "pose_error_contact": pose_errors([s for s in steps if s["ignore_collisions"]]),
        "variations": per_variation(records),
        "phrasings": per_phrasing(records),
    }


def per_variation(records: list[dict]) -> dict[str, dict]:
    """Success per variation (keys: the variation's index as text, as JSON keeps it); journals of older
    rvt2 have no variations: theirs is 0, the only one."""
    out = {}
    for v in sorted({r.get("variation", 0) for r in records}):
        mine = [r for r in records if r.get("variation", 0) == v]
        wins = sum(r["success"] for r in mine)
        out[str(v)] = {"episodes": len(mine), "successes": wins, "success_rate": wins / len(mine),
                       "wrong": sum(r.get("wrong") is not None for r in mine)}
    return out


def build_report(records: list[dict], meta: dict) -> dict:
    """Per task and source (policy / oracle): success with its interval, failures, pose errors."""
    records = sorted(records, key=lambda r: (SOURCES.index(r["source"]), r["task"], r["seed"]))
    tasks = sorted({r["task"] for r in records})
    insertion = {task: _is_insertion(task) for task in tasks}
    records = [{**r, "reason": failure_reason(r, insertion[r["task"]])} for r in records]
    sources = [s for s in SOURCES if any(r["source"] == s for r in records)]
    report = {**meta, "tasks": {}, "episodes": records}
    for task in tasks:
        report["tasks"][task] = {s: summarize([r for r in records if r["task"] == task and r["source"] == s], insertion[task])
                                 for s in sources if any(r["task"] == task and r["source"] == s for r in records)}
    if len(tasks) > 1:
        report["average"] = {s: sum(report["tasks"][t][s]["success_rate"] for t in tasks if s in report["tasks"][t]) / len(tasks)
                             for s in sources}
    per_source = {s: summarize([r for r in records if r["source"] == s]) for s in sources}
    for key in ("pose_error", "pose_error_free", "pose_error_contact"):
        report[key] = {s: per_source[s][key] for s in sources}
    return report


def per_phrasing(records: list[dict]) -> dict[str, dict]:
    """Success per instruction template (`phrasing`), e.g. "open {drawer} drawer": which phrasings a policy
    reads, over all the variations they name. An instruction no template of the task makes (a user's own
    `--instruction`, a task this rvt2 does not know) counts under its own text."""
    out = {}
    for r in records:
        key, held_out = phrasing(r["task"], r.get("variation", 0), r.get("instruction") or "-")
        entry = out.setdefault(key, {"episodes": 0, "successes": 0, "wrong": 0, "held_out": held_out})
        entry["episodes"] += 1
        entry["successes"] += bool(r["success"])
        entry["wrong"] += r.get("wrong") is not None
    for entry in out.values():
        entry["success_rate"] = entry["successes"] / entry["episodes"]
    return dict(sorted(out.items()))


def phrasing(task: str, variation: int, instruction: str) -> tuple[str, bool]:
    """The template (trained, or a held-out paraphrase: True) that makes `instruction` for this variation, or
    the text itself (False)."""
    try:
        known = get_task(task)
        values = known.variation_values(variation)
    except (UserError, IndexError):
        return instruction, False
    for template in known.instructions:
        if template.format(**values) == instruction:
            return template, False
    return next(((t, True) for t in known.paraphrases if t.format(**values) == instruction), (instruction, False))


def _is_insertion(task: str) -> bool:
    try:
        return get_task(task).insertion
    except UserError:  # a task of an older rvt2, kept in a journal: no insertion check
        return False


def _values(task: str, variation: int) -> str:
    """A variation's placeholder values, e.g. "color=pink" ("-" for a task this rvt2 does not know)."""
    try:
        values = get_task(task).variation_values(variation)
    except (UserError, IndexError):
        return "-"
    return ", ".join(f"{k}={v}" for k, v in sorted(values.items())) or "-"


def _mm(stats: dict) -> str:
    return "-" if stats["median"] is None else f"{stats['median']:.2f} / {stats['p95']:.2f}"


def markdown(report: dict) -> str:
    sources = [s for s in SOURCES if any(s in r for r in report["tasks"].values())]
    head = ("| task | " + " | ".join(f"{s} success (95% CI) | {s} keyframes" for s in sources)
            + " | policy failures | " + " | ".join(f"{s} error at rest, mm (median / p95) | {s} deg (median / p95)" for s in sources)
            + " | policy unreached / replans |")
    lines = [f"# Evaluation: {report.get('checkpoint') or 'oracle only'}", "",
             f"Seeds from {report['seed']}, {report['episodes_per_task']} episodes per task, keyframe budget "
             f"{report['keyframe_budget']}, control steps up to {report.get('step_budget_scale', 1):g} x each task's max_steps."]
    if report.get("paraphrases"):
        lines += ["", "Instructions: each task's held-out paraphrases (never seen in training)."]
    if report.get("first_phrasing"):
        lines += ["", "Instructions: each variation's first trained phrasing (RLBench's first description, "
                      "as PerAct, RVT and RVT-2 evaluate)."]
    if report.get("variations", "all") != "all":
        lines += ["", f"Variations: {report['variations']} only."]
    if report.get("untrained_tasks"):
        lines += ["", f"Not in the checkpoint's training set (a generalisation test): {', '.join(report['untrained_tasks'])}."]
    if report.get("shared_policy"):
        lines += ["", "Keyframes from one copy of the policy in the main process, shared by the workers (--shared-policy)."]
    if report.get("cuda_graph"):
        lines += ["", "Each worker's policy step replayed as one CUDA graph (--cuda-graph)."]
    lines += ["", head, "|" + "---|" * (4 * len(sources) + 3)]
    for task, per in report["tasks"].items():
        cells = []
        for s in sources:
            r = per.get(s)
            cells += [f"{r['success_rate']:.0%} ({r['ci95'][0]:.0%}-{r['ci95'][1]:.0%}), n={r['episodes']}" if r else "-",
                      f"{r['mean_keyframes']:.1f}" if r else "-"]
        policy = per.get("policy", {})
        fails = ", ".join(f"{k} {v}" for k, v in policy.get("failures", {}).items() if v)
        errors = []
        for s in sources:
            r = per.get(s)
            errors += [_mm(r["pose_error"]["position_mm"]) if r else "-", _mm(r["pose_error"]["rotation_deg"]) if r else "-"]
        unreached = f"{policy['unreached_keyframes']} / {policy['replans']}" if policy else "-"
        lines.append(f"| {task} | " + " | ".join(cells) + f" | {fails} | " + " | ".join(errors) + f" | {unreached} |")
    if "average" in report:
        lines.append("| **average** | " + " | ".join(f"{report['average'].get(s, 0):.0%} | " for s in sources) + " |")
    if report.get("step_budget_scale", 1) != 1:
        within = "; ".join(f"{task} " + ", ".join(f"{s} {r['successes_within_task_steps']}/{r['episodes']}"
                                                   for s, r in per.items() if "successes_within_task_steps" in r)
                           for task, per in report["tasks"].items())
        lines += ["", f"Successes within each task's own max_steps (a budget of 1 x): {within}."]
    grids = report.get("search_grids") or {}
    searches = [f"{task} {s}: {r['insertion_search']['found']} of {r['insertion_search']['searched']} "
                f"({r['insertion_search']['probes']} probes"
                + (f"; grid {grids[task]['pitch_mm']:g} mm, retract {grids[task]['retract_mm']:g} mm" if task in grids else "")
                + ")"
                for task, per in report["tasks"].items() for s, r in per.items() if r.get("insertion_search", {}).get("searched")]
    if report.get("insertion_search") is False:
        lines += ["", "Insertion search off (--no-insertion-search): insertions were pushed straight to their keyframes."]
    elif searches:
        lines += ["", "Insertion search (rvt2cli.eval.search): insertions that stopped at a face and then found the hole, "
                  "of those searched: " + "; ".join(searches) + "."]
    varied = {task: per for task, per in report["tasks"].items()
              if any(len(r.get("variations", {})) > 1 for r in per.values())}
    if varied:
        lines += ["", "Success per variation (tasks with several; wrong: the episode ended with another variation's "
                  "object taken or target reached):", "", "| task | source | variation | values | success | wrong |",
                  "|---|---|---|---|---|---|"]
        for task, per in varied.items():
            for s in sources:
                for v, r in per.get(s, {}).get("variations", {}).items():
                    lines.append(f"| {task} | {s} | {v} | {_values(task, int(v))} | {r['successes']}/{r['episodes']} "
                                 f"({r['success_rate']:.0%}) | {r['wrong']} |")
    worded = {task: per for task, per in report["tasks"].items()
              if any(len(r.get("phrasings", {})) > 1 for r in per.values())}
    if worded:
        lines += ["", "Success per phrasing (tasks with several; each template over the variations it names; "
                  "held out: a paraphrase no training demo used):", "", "| task | source | phrasing | success | wrong |",
                  "|---|---|---|---|---|"]
        for task, per in worded.items():
            for s in sources:
                for text, r in per.get(s, {}).get("phrasings", {}).items():
                    mark = " (held out)" if r["held_out"] else ""
                    lines.append(f"| {task} | {s} | {text}{mark} | {r['successes']}/{r['episodes']} "
                                 f"({r['success_rate']:.0%}) | {r['wrong']} |")
    lines += ["", "Why episodes failed (rvt2cli.eval.taxonomy), per task and source; for insertion tasks the "
              "median gap to success, mm, of the failed episodes' closest approach with the object in hand:", "",
              "| task | source | " + " | ".join(REASONS) + " | gap mm | unreached per episode |",
              "|---|---|" + "---|" * (len(REASONS) + 2)]
    for task, per in report["tasks"].items():
        for s in sources:
            r = per.get(s)
            if r:
                gap = r["insertion_gap_mm"]["median"]
                lines.append(f"| {task} | {s} | " + " | ".join(str(r["reasons"].get(k, 0)) for k in REASONS)
                             + f" | {'-' if gap is None else f'{gap:.1f}'} | {r['unreached_per_episode']:.2f} |")
    lines += ["", "Error at rest: distance between the TCP, once the arm has come to rest, and the keyframe's pose, "
              "over every keyframe the executor reached. By kind of keyframe, mm (median / p95) and deg (median / p95):", "",
              "| source | keyframes in free space (avoiding collisions) | mm | deg | keyframes into contact (ignoring collisions) | mm | deg |",
              "|---|---|---|---|---|---|---|"]
    for s in sources:
        free, contact = report["pose_error_free"][s], report["pose_error_contact"][s]
        lines.append(f"| {s} | {free['keyframes']} | {_mm(free['position_mm'])} | {_mm(free['rotation_deg'])} | "
                     f"{contact['keyframes']} | {_mm(contact['position_mm'])} | {_mm(contact['rotation_deg'])} |")
    return "\n".join(lines) + "\n"


def bar_chart(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(report["tasks"])
    sources = [s for s in SOURCES if any(s in r for r in report["tasks"].values())]
    if not sources:  # no episode finished (e.g. the simulators died at once): nothing to draw
        return
    fig, ax = plt.subplots(figsize=(max(4, 1.2 * len(tasks) + 1), 3.5))
    width = 0.8 / len(sources)
    for i, s in enumerate(sources):
        rates = [report["tasks"][t].get(s, {}).get("success_rate", 0) for t in tasks]
        intervals = [report["tasks"][t].get(s, {"ci95": [r, r]})["ci95"] for r, t in zip(rates, tasks)]
        err = [[max(0.0, r - lo) for r, (lo, _) in zip(rates, intervals)], [max(0.0, hi - r) for r, (_, hi) in zip(rates, intervals)]]
        ax.bar([x + i * width for x in range(len(tasks))], rates, width, yerr=err, capsize=3, label=s)
    ax.set_xticks([x + width * (len(sources) - 1) / 2 for x in range(len(tasks))], tasks, rotation=30, ha="right")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("success rate")
    ax.legend()
    fig.tight_layout()
    with atomic_open(path) as f:
        fig.savefig(f, format="png", dpi=120)
    plt.close(fig)


def write_report(report: dict, out_dir: Path) -> None:
    with atomic_open(out_dir / "eval.json", "w") as f:
        json.dump(report, f, indent=2)
    with atomic_open(out_dir / "eval.md", "w") as f:
        f.write(markdown(report))
    bar_chart(report, out_dir / "eval.png")
