"""The table and bar chart of docs/RESULTS.md, from `rvt2 eval` reports and the expert's success.

    python -m benchmarks.results_table --policy "LABEL=EVAL_DIR" [--policy ...] --oracle EVAL_DIR \
        --expert expert.json [--chart docs/results.png] [--json benchmarks/results/results.json]

EVAL_DIR is an `rvt2 eval --out` folder (its eval.json); the --oracle one was run with `--oracle`;
expert.json is `python -m benchmarks.record_bench --first-seed 10000 --seeds 25 --episodes 0 --json ...`.
The last column compares the first --policy with the oracle.
"""

import argparse
import json
from pathlib import Path


def _rate(report: dict, task: str, source: str) -> dict:
    entry = report["tasks"][task][source]
    return {"successes": entry["successes"], "episodes": entry["episodes"], "rate": entry["success_rate"],
            "ci95": entry["ci95"], "failures": entry["failures"]}


def collect(policies: dict[str, dict], oracle: dict, expert: dict) -> dict:
    expert_by_task = {e["task"]: e for e in expert["expert"]}
    rows = []
    for task in sorted(oracle["tasks"]):
        rows.append({"task": task, "policies": {label: _rate(report, task, "policy") for label, report in policies.items()},
                     "oracle": _rate(oracle, task, "oracle"),
                     "expert": {"rate": expert_by_task[task]["success"], "episodes": expert_by_task[task]["seeds"]}})
    average = {label: sum(r["policies"][label]["rate"] for r in rows) / len(rows) for label in policies}
    average["oracle"] = sum(r["oracle"]["rate"] for r in rows) / len(rows)
    average["expert"] = sum(r["expert"]["rate"] for r in rows) / len(rows)
    first = next(iter(policies.values()))
    return {"seeds": f"{first['seed']}-{first['seed'] + first['episodes_per_task'] - 1}", "labels": list(policies),
            "rows": rows, "average": average}


def markdown(results: dict) -> str:
    def cell(r):
        lo, hi = r["ci95"]
        return f"{r['rate']:.0%} ({r['successes']}/{r['episodes']}; {lo:.0%}-{hi:.0%})"

    labels = results["labels"]
    lines = ["| task | " + " | ".join(labels) + " | oracle (same executor) | scripted expert | "
             f"{labels[0]} / oracle |", "|---" * (len(labels) + 4) + "|"]
    for r in results["rows"]:
        first = r["policies"][labels[0]]["rate"]
        ratio = f"{first / r['oracle']['rate']:.2f}" if r["oracle"]["rate"] else "-"
        lines.append(f"| {r['task']} | " + " | ".join(cell(r["policies"][label]) for label in labels)
                     + f" | {cell(r['oracle'])} | {r['expert']['rate']:.0%} | {ratio} |")
    a = results["average"]
    lines.append("| **average** | " + " | ".join(f"**{a[label]:.0%}**" for label in labels)
                 + f" | **{a['oracle']:.0%}** | **{a['expert']:.0%}** | |")
    return "\n".join(lines)


def chart(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    tasks = [r["task"] for r in results["rows"]]
    series = [(label, [r["policies"][label]["rate"] for r in results["rows"]]) for label in results["labels"]]
    series += [("oracle", [r["oracle"]["rate"] for r in results["rows"]]), ("expert", [r["expert"]["rate"] for r in results["rows"]])]
    width = 0.8 / len(series)
    x = np.arange(len(tasks))
    fig, ax = plt.subplots(figsize=(12, 4.2))
    for i, (label, rates) in enumerate(series):
        ax.bar(x + (i - (len(series) - 1) / 2) * width, [100 * v for v in rates], width, label=label)
    ax.set_xticks(x, tasks, rotation=15)
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 115)
    ax.set_title(f"Closed-loop success, 25 unseen seeds per task ({results['seeds']})")
    ax.legend(ncol=len(series), fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", action="append", required=True, metavar="LABEL=EVAL_DIR")
    parser.add_argument("--oracle", required=True, metavar="EVAL_DIR")
    parser.add_argument("--expert", required=True)
    parser.add_argument("--chart")
    parser.add_argument("--json")
    args = parser.parse_args()
    load = lambda folder: json.loads((Path(folder) / "eval.json").read_text())  # noqa: E731
    policies = {label: load(folder) for label, folder in (p.split("=", 1) for p in args.policy)}
    results = collect(policies, load(args.oracle), json.loads(Path(args.expert).read_text()))
    print(markdown(results))
    if args.chart:
        chart(results, Path(args.chart))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
