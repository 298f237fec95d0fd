"""A results table and bar chart from `rvt2 eval` reports and the oracle benchmark.

    python -m benchmarks.results_table --policy "LABEL=EVAL_DIR[+EVAL_DIR...][,EVAL_DIR...]" [--policy ...] \
        (--oracle-bench oracle.json | --oracle EVAL_DIR --expert expert.json) \
        [--previous "LABEL=results.json[#COLUMN]"] [--chart results.png] [--json results.json]

EVAL_DIR is an `rvt2 eval --out` folder; several joined with + are one evaluation over all their seeds
(their episode records are merged and summarised by the same code `rvt2 eval` uses). EVAL_DIR@FIRST-LAST
takes that evaluation's seeds FIRST to LAST only (one range of a 100-seed evaluation); EVAL_DIR#first takes
the episodes instructed with their variation's first trained phrasing only (the phrasing the paper trains and
evaluates with), #others the rest. Several models
(training seeds) separated by commas are one row entry: their episodes pooled (rate and Wilson interval
over all of them) and the spread between the models' rates beside it. oracle.json is
`python -m benchmarks.oracle_bench --json ...` (oracle and expert on the same seeds); the older pair
--oracle/--expert takes an `rvt2 eval --oracle` folder and `benchmarks.record_bench --json` output.
--previous adds a policy column of an earlier results.json (its first, or the one named after #) for comparison. --paper
FILE#MODEL adds a published column (`benchmarks/paper_rlbench18.toml#rvt2`: the RVT-2 paper's mean and standard deviation
over its four evaluations) and, for the first --paper, the first policy's difference from it in points. The last column
compares the first --policy with the oracle. --paired adds, for each other --policy, the episodes (task and seed)
that succeed in the first only and in it only, with the exact McNemar test of them.
"""

import argparse
import json
import tomllib
from pathlib import Path

from rvt2cli.eval.journal import NAME as JOURNAL, copy_in, read_journal, read_text
from rvt2cli.eval.report import build_report, wilson_interval


def load_records(dirs: str) -> tuple[list[dict], int]:
    """The policy's episode records of one or more eval folders (merged), and the first seed they cover."""
    records, seeds = [], []
    for item in dirs.split("+"):
        item, phrasing = phrasing_filter(item)
        folder, first, last = seed_range(item)
        plan, episodes = read_journal(journal_of(Path(folder)))
        records += [e for e in episodes if e["source"] == "policy" and first <= e["seed"] <= last and phrasing(e)]
        seeds.append(max(plan["seed"], first))
    return records, min(seeds)


def report_of(records: list[dict], seed: int) -> dict:
    """One report of a policy's episode records (`load_records`)."""
    per_task = len({r["seed"] for r in records if r["task"] == records[0]["task"]})
    return build_report(records, {"seed": seed, "episodes_per_task": per_task})


def load_policy(dirs: str) -> dict:
    """One report from one or more eval folders (their episodes merged)."""
    return report_of(*load_records(dirs))


def paired(first: list[dict], other: list[dict]) -> dict:
    """Two models on the same episodes (task and seed): how many succeed in one only, and the exact McNemar test
    of those discordant episodes (two-sided binomial, half and half under no difference)."""
    from scipy.stats import binomtest

    def by_episode(records):
        return {(r["task"], r["seed"]): bool(r["success"]) for r in records}

    a, b = by_episode(first), by_episode(other)
    both = sorted(a.keys() & b.keys())
    if not both:
        raise SystemExit("results_table: error: --paired: the two evaluations share no episode (task and seed); "
                         "give evaluations of the same seeds")
    only_first = sum(a[k] and not b[k] for k in both)
    only_other = sum(b[k] and not a[k] for k in both)
    discordant = only_first + only_other
    return {"episodes": len(both), "only_first": only_first, "only_other": only_other,
            "p": binomtest(only_first, discordant).pvalue if discordant else 1.0}


def paired_markdown(first_label: str, comparisons: dict[str, dict]) -> str:
    lines = [f"| against {first_label} | episodes paired | succeed only in {first_label} | only in this | exact McNemar p |",
             "|---|---|---|---|---|"]
    for label, c in comparisons.items():
        lines.append(f"| {label} | {c['episodes']} | {c['only_first']} | {c['only_other']} | {p_value(c['p'])} |")
    return "\n".join(lines)


def p_value(p: float) -> str:
    """Two significant digits; a p too small for a double (it underflows to 0) as a bound, never as 0."""
    return f"{p:.2g}" if p > 0 else "< 1e-300"


def seed_range(item: str) -> tuple[str, float, float]:
    """EVAL_DIR or EVAL_DIR@FIRST-LAST -> (the folder, the first and last seed taken)."""
    folder, at, seeds = item.rpartition("@")
    if not at:
        return item, float("-inf"), float("inf")
    first, _, last = seeds.partition("-")
    if not (first.isdigit() and last.isdigit()) or int(first) > int(last):
        raise SystemExit(f"results_table: {item!r}: give seeds as EVAL_DIR@FIRST-LAST, e.g. evals/x@10000-10049")
    return folder, int(first), int(last)


def phrasing_filter(item: str):
    """EVAL_DIR[@...]#first or #others -> (the rest, a test of an episode): only the episodes instructed with
    their variation's first trained phrasing (the paper's, RLBench's descriptions[0]), or only the others."""
    rest, hash_, which = item.rpartition("#")
    if not hash_:
        return item, lambda episode: True
    if which not in ("first", "others"):
        raise SystemExit(f"results_table: {item!r}: the phrasing after # is first or others, e.g. evals/x#first")
    from rvt2cli.tasks import get_task

    def is_first(episode: dict) -> bool:
        return episode["instruction"] == get_task(episode["task"]).first_phrasing(episode.get("variation", 0))

    return rest, is_first if which == "first" else (lambda episode: not is_first(episode))


def journal_of(folder: Path) -> Path:
    """An eval folder's journal: `rvt2 eval`'s episodes.jsonl, or the compressed copy kept in benchmarks/results."""
    if (path := copy_in(folder, JOURNAL)) is None:
        raise SystemExit(f"results_table: {folder} has no {JOURNAL}(.gz, .xz); give an `rvt2 eval --out` folder")
    return path


def load_models(models: str) -> list[dict]:
    """One report per model (training seed); a model's eval folders are joined with +."""
    return [load_policy(dirs) for dirs in models.split(",")]


def _rate(successes: int, episodes: int) -> dict:
    return {"successes": successes, "episodes": episodes, "rate": successes / episodes if episodes else 0.0,
            "ci95": list(wilson_interval(successes, episodes))}


def _pooled(reports: list[dict], task: str) -> dict:
    """One task over several models: pooled rate and interval, each model's rate and their spread."""
    per_model = [r["tasks"][task]["policy"] for r in reports]
    entry = {**_rate(sum(p["successes"] for p in per_model), sum(p["episodes"] for p in per_model)),
             "failures": {}, "unreached": sum(p["unreached_keyframes"] for p in per_model),
             "replans": sum(p["replans"] for p in per_model)}
    for p in per_model:
        for reason, n in p["failures"].items():
            entry["failures"][reason] = entry["failures"].get(reason, 0) + n
    if len(per_model) > 1:
        rates = [p["successes"] / p["episodes"] for p in per_model]
        entry["models"] = rates
        entry["spread"] = max(rates) - min(rates)
    return entry


def load_paper(arg: str) -> tuple[str, dict]:
    """FILE#MODEL: one model's published success per task, {task: {"mean": %, "std": %}} (see paper_rlbench18.toml)."""
    path, _, model = arg.partition("#")
    figures = tomllib.loads(Path(path).read_text())
    if model not in figures:
        known = ", ".join(k for k, v in figures.items() if isinstance(v, dict))
        raise SystemExit(f"results_table: error: {path} has no model {model!r}; give FILE#MODEL with one of: {known}")
    return f"paper: {model}", {task: {"mean": v[0], "std": v[1]} for task, v in figures[model].items() if task != "average"}


def collect(policies: dict[str, list[dict]], oracle: dict[str, dict], expert: dict[str, dict], previous: dict,
            papers: dict | None = None) -> dict:
    papers = papers or {}
    rows = []
    # the first policy's tasks (an evaluation of some tasks only gets rows for those); every column needs them
    tasks = sorted(next(iter(policies.values()))[0]["tasks"])
    for label, reports in policies.items():
        for report in reports:
            lacking = [t for t in tasks if t not in report["tasks"]]
            if lacking:
                raise SystemExit(f"results_table: error: --policy {label!r} has no episodes of {lacking[0]}, which the "
                                 "first --policy has; give evaluations of the same tasks")
    lacking = [t for t in tasks if t not in oracle]
    if lacking:
        raise SystemExit(f"results_table: error: the oracle has no episodes of {lacking[0]}; give an oracle of every task evaluated")
    for task in tasks:
        entry = {"task": task, "policies": {}, "oracle": oracle[task], "expert": expert[task],
                 "papers": {label: figures.get(task) for label, figures in papers.items()}}
        for label, reports in policies.items():
            entry["policies"][label] = _pooled(reports, task)
        for label, rows_before in previous.items():
            entry["policies"][label] = rows_before[task]
        rows.append(entry)
    labels = list(policies) + list(previous)
    average = {label: sum(r["policies"][label]["rate"] for r in rows) / len(rows) for label in labels}
    average["oracle"] = sum(r["oracle"]["rate"] for r in rows) / len(rows)
    average["expert"] = sum(r["expert"]["rate"] for r in rows) / len(rows)
    for label in papers:
        given = [r["papers"][label]["mean"] for r in rows if r["papers"][label]]
        average[label] = sum(given) / len(given) / 100 if given else None
    first = next(iter(policies.values()))[0]
    return {"seeds": f"{first['seed']}-{first['seed'] + first['episodes_per_task'] - 1}", "labels": labels,
            "papers": list(papers), "rows": rows, "average": average}


def from_oracle_bench(path: str) -> tuple[dict, dict]:
    bench = json.loads(Path(path).read_text())
    oracle, expert = {}, {}
    for t in bench["tasks"]:
        oracle[t["task"]] = {**_rate(sum(t["oracle_per_seed"]), t["seeds"]), "agreement": t["agreement"]}
        expert[t["task"]] = _rate(sum(s == "success" for s in t["expert_per_seed"]), t["seeds"])
    return oracle, expert


def from_eval_and_record(oracle_dir: str, expert_path: str) -> tuple[dict, dict]:
    plan, episodes = read_journal(journal_of(Path(oracle_dir)))
    report = build_report([e for e in episodes if e["source"] == "oracle"], {"seed": plan["seed"]})
    expert_json = json.loads(Path(expert_path).read_text())
    oracle = {t: _rate(v["oracle"]["successes"], v["oracle"]["episodes"]) for t, v in report["tasks"].items()}
    expert = {e["task"]: _rate(round(e["success"] * e["seeds"]), e["seeds"]) for e in expert_json["expert"]}
    return oracle, expert


def load_previous(arg: str) -> tuple[str, dict]:
    """LABEL=RESULTS_JSON[#COLUMN]: a policy column of an earlier results.json, or its compressed copy (default: its
    first)."""
    label, path = arg.split("=", 1)
    path, _, column = path.partition("#")
    results = json.loads(read_text(Path(path)))
    column = column or results["labels"][0]
    return label, {r["task"]: r["policies"][column] for r in results["rows"]}


def markdown(results: dict) -> str:
    def cell(r):
        lo, hi = r["ci95"]
        spread = f"; models {'/'.join(f'{m:.0%}' for m in r['models'])}" if "models" in r else ""
        return f"{r['rate']:.0%} ({r['successes']}/{r['episodes']}; {lo:.0%}-{hi:.0%}{spread})"

    def published(figure):
        return f"{figure['mean']:g} ± {figure['std']:g}" if figure else "-"

    def points(rate, figure):  # the policy's rate against a published mean, in points
        return f"{100 * rate - figure['mean']:+.0f}" if figure else "-"

    labels, papers = results["labels"], results.get("papers", [])
    against = [f"{labels[0]} - {papers[0]} (points)"] if papers else []
    header = [*labels, *papers, *against, "oracle (same executor)", "scripted expert", f"{labels[0]} / oracle"]
    lines = ["| task | " + " | ".join(header) + " |", "|---" * (len(header) + 1) + "|"]
    for r in results["rows"]:
        first = r["policies"][labels[0]]["rate"]
        ratio = f"{first / r['oracle']['rate']:.2f}" if r["oracle"]["rate"] else "-"
        cells = [cell(r["policies"][label]) for label in labels] + [published(r["papers"][p]) for p in papers]
        cells += [points(first, r["papers"][papers[0]])] if papers else []
        lines.append(f"| {r['task']} | " + " | ".join(cells) + f" | {cell(r['oracle'])} | {cell(r['expert'])} | {ratio} |")
    a = results["average"]
    cells = [f"**{a[label]:.0%}**" for label in labels] + [f"**{100 * a[p]:.1f}**" if a[p] is not None else "-" for p in papers]
    cells += [f"{100 * (a[labels[0]] - a[papers[0]]):+.1f}" if a[papers[0]] is not None else "-"] if papers else []
    lines.append("| **average** | " + " | ".join(cells) + f" | **{a['oracle']:.0%}** | **{a['expert']:.0%}** | |")
    return "\n".join(lines)


def chart(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    tasks = [r["task"] for r in results["rows"]]
    series = [(label, [r["policies"][label]["rate"] for r in results["rows"]]) for label in results["labels"]]
    series += [(paper, [(r["papers"][paper] or {"mean": np.nan})["mean"] / 100 for r in results["rows"]])
               for paper in results.get("papers", [])]
    series += [("oracle", [r["oracle"]["rate"] for r in results["rows"]]), ("expert", [r["expert"]["rate"] for r in results["rows"]])]
    width = 0.8 / len(series)
    x = np.arange(len(tasks))
    fig, ax = plt.subplots(figsize=(max(12, 0.75 * len(tasks)), 4.8))
    for i, (label, rates) in enumerate(series):
        ax.bar(x + (i - (len(series) - 1) / 2) * width, [100 * v for v in rates], width, label=label)
    ax.set_xticks(x, tasks, rotation=30 if len(tasks) > 8 else 15, ha="right" if len(tasks) > 8 else "center")
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 115)
    ax.set_title(f"Closed-loop success on unseen seeds (from {results['seeds'].split('-')[0]}; episodes per task in docs/RESULTS.md)")
    ax.legend(ncol=len(series), fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", action="append", required=True, metavar="LABEL=EVAL_DIR[+EVAL_DIR][,EVAL_DIR]")
    parser.add_argument("--oracle-bench", metavar="ORACLE_JSON")
    parser.add_argument("--oracle", metavar="EVAL_DIR")
    parser.add_argument("--expert")
    parser.add_argument("--previous", action="append", default=[], metavar="LABEL=RESULTS_JSON[#COLUMN]")
    parser.add_argument("--paper", action="append", default=[], metavar="FILE#MODEL",
                        help="a published column, e.g. benchmarks/paper_rlbench18.toml#rvt2 (repeatable)")
    parser.add_argument("--paired", action="store_true",
                        help="below the table, each other --policy against the first, episode by episode")
    parser.add_argument("--chart")
    parser.add_argument("--json")
    args = parser.parse_args()
    if not args.oracle_bench and not (args.oracle and args.expert):
        parser.error("give the oracle and expert columns: --oracle-bench ORACLE_JSON, or --oracle EVAL_DIR with --expert RECORD_JSON")
    specs = [p.split("=", 1) for p in args.policy]
    if args.paired and any("," in models for _, models in specs):
        parser.error("--paired compares single models: give each --policy without commas")
    # each model's episodes, read once: its report, and the episode-by-episode comparison (--paired)
    read = {label: [load_records(dirs) for dirs in models.split(",")] for label, models in specs}
    policies = {label: [report_of(*model) for model in models] for label, models in read.items()}
    if args.oracle_bench:
        oracle, expert = from_oracle_bench(args.oracle_bench)
    else:
        oracle, expert = from_eval_and_record(args.oracle, args.expert)
    results = collect(policies, oracle, expert, dict(load_previous(p) for p in args.previous),
                      dict(load_paper(p) for p in args.paper))
    print(markdown(results))
    if args.paired:
        (first_label, [(first, _)]), *others = read.items()
        comparisons = {label: paired(first, records) for label, [(records, _)] in others}
        results["paired"] = {"against": first_label, **comparisons}
        print()
        print(paired_markdown(first_label, comparisons))
    if args.chart:
        chart(results, Path(args.chart))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
