"""Evaluation reports: eval.json, eval.md and a bar chart of success per task (policy vs oracle)."""

import json
import math
from pathlib import Path

from rvt2cli.atomic import atomic_open
from rvt2cli.eval.rollout import FAILURE_KINDS, Outcome


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% confidence interval of a success rate (Wilson score interval; sane at 0 and n)."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def summarize(outcomes: list[Outcome]) -> dict:
    n = len(outcomes)
    wins = sum(o.success for o in outcomes)
    lo, hi = wilson_interval(wins, n)
    return {
        "episodes": n, "successes": wins, "success_rate": wins / n if n else 0.0, "ci95": [lo, hi],
        "mean_keyframes": sum(o.keyframes for o in outcomes) / n if n else 0.0,
        "failures": {kind: sum(o.failure == kind for o in outcomes) for kind in FAILURE_KINDS},
    }


def build_report(results: dict[str, dict[str, list[Outcome]]], meta: dict) -> dict:
    """results[source][task] -> outcomes, source in {"policy", "oracle"}."""
    tasks = sorted({t for per_task in results.values() for t in per_task})
    report = {**meta, "tasks": {}, "episodes": []}
    for task in tasks:
        report["tasks"][task] = {source: summarize(per_task[task]) for source, per_task in results.items() if task in per_task}
    for source, per_task in results.items():
        for outcomes in per_task.values():
            for o in outcomes:
                report["episodes"].append({"source": source, "task": o.task, "seed": o.seed, "success": o.success,
                                           "failure": o.failure, "keyframes": o.keyframes, "control_steps": o.control_steps,
                                           "collision_fallbacks": o.collision_fallbacks,
                                           "unreached_keyframes": sum(not s.reached for s in o.steps),
                                           "instruction": o.instruction, "error": o.error})
    sources = list(results)
    if len(tasks) > 1:
        report["average"] = {s: sum(report["tasks"][t][s]["success_rate"] for t in tasks if s in report["tasks"][t]) / len(tasks)
                             for s in sources}
    return report


def markdown(report: dict) -> str:
    sources = [s for s in ("policy", "oracle") if any(s in r for r in report["tasks"].values())]
    head = "| task | " + " | ".join(f"{s} success (95% CI) | {s} keyframes" for s in sources) + " | policy failures |"
    lines = [f"# Evaluation: {report.get('checkpoint') or 'oracle only'}", "",
             f"Seeds from {report['seed']}, {report['episodes_per_task']} episodes per task, keyframe budget {report['keyframe_budget']}.", "",
             head, "|" + "---|" * (2 * len(sources) + 2)]
    for task, per in report["tasks"].items():
        cells = []
        for s in sources:
            r = per.get(s)
            cells += [f"{r['success_rate']:.0%} ({r['ci95'][0]:.0%}-{r['ci95'][1]:.0%}), n={r['episodes']}" if r else "-",
                      f"{r['mean_keyframes']:.1f}" if r else "-"]
        fails = per.get("policy", {}).get("failures", {})
        lines.append(f"| {task} | " + " | ".join(cells) + " | " + ", ".join(f"{k} {v}" for k, v in fails.items() if v) + " |")
    if "average" in report:
        lines.append("| **average** | " + " | ".join(f"{report['average'].get(s, 0):.0%} | " for s in sources) + " |")
    return "\n".join(lines) + "\n"


def bar_chart(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(report["tasks"])
    sources = [s for s in ("policy", "oracle") if any(s in r for r in report["tasks"].values())]
    fig, ax = plt.subplots(figsize=(max(4, 1.2 * len(tasks) + 1), 3.5))
    width = 0.8 / len(sources)
    for i, s in enumerate(sources):
        rates = [report["tasks"][t].get(s, {}).get("success_rate", 0) for t in tasks]
        err = [[r - report["tasks"][t].get(s, {"ci95": [0, 0]})["ci95"][0] for r, t in zip(rates, tasks)],
               [report["tasks"][t].get(s, {"ci95": [0, 0]})["ci95"][1] - r for r, t in zip(rates, tasks)]]
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
    out_dir.mkdir(parents=True, exist_ok=True)
    with atomic_open(out_dir / "eval.json", "w") as f:
        json.dump(report, f, indent=2)
    with atomic_open(out_dir / "eval.md", "w") as f:
        f.write(markdown(report))
    bar_chart(report, out_dir / "eval.png")
