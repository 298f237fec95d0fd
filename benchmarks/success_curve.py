"""Closed-loop success against training time (the paper's "training time vs success" figure), from experiment folders.

    python -m benchmarks.success_curve --model "LABEL=DIR[+DIR...]" [--model ...] [--seeds FIRST[,FIRST...]] \
        [--x minutes|steps] [--chart docs/img/success_curve.png] [--json curve.json]

DIR is an experiment's folder (`python -m benchmarks.experiment --out`, or its copy under benchmarks/results/):
its training (runs/seed0/ or train/: run.json and train.csv, compressed or not) and its evaluations, of the last
checkpoint (evals/seed0_fromFIRST) and of earlier ones (evals/seed0_fromFIRST_stepS: `--eval-steps`). Several
folders joined with + are one model's points, e.g. schedules of different lengths. A point is a checkpoint: its
step, the training's wall time up to it (run.json's seconds, shared out over the steps by train.csv's logged
rates, so validation and checkpoint pauses land where they happened) and its success over the evaluation's
episodes with a Wilson interval. Runs on different machines compare by steps (`--x steps`), not by minutes.
Only evaluations on seeds from FIRST count (default: the one first seed all
of a model's folders share, e.g. validation seeds 20000); several, e.g. 10000,10050 (the reported seeds' two ranges),
pool each checkpoint's evaluations from those seeds into one point.
"""

import argparse
import csv
import io
import json
import re
import sys
from pathlib import Path

from benchmarks.results_table import journal_of
from rvt2cli.eval.journal import copy_in, read_journal, read_text
from rvt2cli.eval.report import wilson_interval

EVAL_FOLDER = re.compile(r"seed(?P<seed>\d+)_from(?P<first>\d+)(?:_step(?P<step>\d+))?")


def _text(folder: Path, name: str) -> str:
    if (path := copy_in(folder, name)) is None:
        raise SystemExit(f"success_curve: {folder} has no {name}(.gz, .xz); give an experiment folder (runs/seed0/ or train/)")
    return read_text(path)


def training(folder: Path, seed: int) -> tuple[dict, list[tuple[int, float]]]:
    """The run's run.json and (step, samples/s) of each train.csv row."""
    run_dir = next((d for d in (folder / "runs" / f"seed{seed}", folder / "train") if d.is_dir()), None)
    if run_dir is None:
        raise SystemExit(f"success_curve: {folder} has neither runs/seed{seed}/ nor train/")
    rows = list(csv.DictReader(io.StringIO(_text(run_dir, "train.csv"))))
    return json.loads(_text(run_dir, "run.json")), [(int(r["step"]), float(r["samples_per_s"])) for r in rows]


def seconds_to(step: int, run: dict, rates: list[tuple[int, float]]) -> float:
    """The training's wall seconds up to `step`: the time before the first step, then the stepping time shared
    out in proportion to each logged interval's time (steps over rate)."""
    setup = run.get("setup_seconds", 0.0)
    intervals, previous = [], 0
    for at, rate in rates:
        intervals.append((at, (at - previous) / rate if rate > 0 else 0.0))
        previous = at
    total = sum(t for _, t in intervals) or 1.0
    done = sum(t for at, t in intervals if at <= step)
    return setup + (run["seconds"] - setup) * done / total


def points(folder: Path, first_seeds: set[int] | None) -> list[dict]:
    """One point per evaluated checkpoint of the experiment folder (all training seeds' runs); with first_seeds,
    a checkpoint's evaluations from those seeds pooled into one point."""
    checkpoints: dict[tuple, list[tuple[Path, int]]] = {}  # (evaluation folder, its first seed)
    for evaluation in sorted((folder / "evals").glob("seed*_from*")):
        match = EVAL_FOLDER.fullmatch(evaluation.name)
        if not match or (first_seeds is not None and int(match["first"]) not in first_seeds):
            continue
        checkpoint = (int(match["seed"]), match["step"]) + ((int(match["first"]),) if first_seeds is None else ())
        checkpoints.setdefault(checkpoint, []).append((evaluation, int(match["first"])))
    found = []
    for (training_seed, step_name, *_), evaluations in checkpoints.items():
        run, rates = training(folder, training_seed)
        step = int(step_name) if step_name else run["steps"]
        policy = [e for evaluation, _ in evaluations for e in read_journal(journal_of(evaluation))[1] if e["source"] == "policy"]
        successes = sum(bool(e["success"]) for e in policy)
        firsts = sorted(first for _, first in evaluations)
        found.append({"folder": "+".join(str(evaluation) for evaluation, _ in evaluations), "training_seed": training_seed, "first_seed": firsts[0],
                      "first_seeds": firsts, "step": step, "train_minutes": seconds_to(step, run, rates) / 60,
                      "episodes": len(policy), "successes": successes, "rate": successes / max(1, len(policy)),
                      "ci95": list(wilson_interval(successes, len(policy)))})
    return found


def curve(model: str, first_seeds: set[int] | None) -> tuple[str, list[dict]]:
    label, equals, dirs = model.partition("=")
    if not equals or not dirs:
        raise SystemExit(f"success_curve: --model {model!r}: give LABEL=DIR[+DIR...]")
    found = [p for d in dirs.split("+") for p in points(Path(d), first_seeds)]
    firsts = {p["first_seed"] for p in found}
    if first_seeds is None and len(firsts) > 1:
        raise SystemExit(f"success_curve: {label}: evaluations from seeds {', '.join(map(str, sorted(firsts)))}; "
                         "choose with --seeds FIRST (or pool ranges: --seeds FIRST,FIRST)")
    if not found:
        raise SystemExit(f"success_curve: {label}: no evaluations (evals/seedN_fromF[_stepS]/) in {dirs}")
    return label, sorted(found, key=lambda p: p["train_minutes"])


def chart(curves: dict[str, list[dict]], path: Path, x_axis: str = "minutes") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, pts in curves.items():
        x = [p["train_minutes"] if x_axis == "minutes" else p["step"] for p in pts]
        y = [100 * p["rate"] for p in pts]
        err = [[100 * (p["rate"] - p["ci95"][0]) for p in pts], [100 * (p["ci95"][1] - p["rate"]) for p in pts]]
        ax.errorbar(x, y, yerr=err, marker="o", capsize=3, label=label)
        for p, xi, yi in zip(pts, x, y):
            if x_axis == "minutes":
                ax.annotate(f"{p['step']:,}", (xi, yi), textcoords="offset points", xytext=(4, -12), fontsize=7)
    ax.set_xlabel("training wall time, minutes" if x_axis == "minutes" else "training steps")
    ax.set_ylabel("closed-loop success, % (95% Wilson)")
    ax.set_ylim(0, 100)
    ax.set_xlim(left=0)  # from no training, as the paper's figure: a short run's point is not shown as the start
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")  # success rises with training: the upper left stays empty
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(curves: dict[str, list[dict]]) -> str:
    lines = ["| model | step | training, min | success | episodes |", "|---|---|---|---|---|"]
    for label, pts in curves.items():
        for p in pts:
            lo, hi = p["ci95"]
            lines.append(f"| {label} | {p['step']:,} | {p['train_minutes']:.1f} | {p['rate']:.1%} ({lo:.1%}-{hi:.1%}) "
                         f"| {p['episodes']} |")
    return "\n".join(lines)


def first_seeds(text: str) -> set[int]:
    try:
        return {int(item) for item in text.split(",")}
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give first seeds as FIRST or FIRST,FIRST (e.g. 10000,10050)") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", action="append", required=True, metavar="LABEL=DIR[+DIR...]")
    parser.add_argument("--seeds", type=first_seeds, metavar="FIRST[,FIRST...]",
                        help="only evaluations on seeds from FIRST (e.g. 20000); several pool their episodes per checkpoint")
    parser.add_argument("--x", choices=("minutes", "steps"), default="minutes",
                        help="the figure's horizontal axis: training wall time (default) or steps")
    parser.add_argument("--chart", type=Path, help="write the figure here (PNG)")
    parser.add_argument("--json", type=Path, help="write the points here")
    args = parser.parse_args(argv)
    curves = dict(curve(model, args.seeds) for model in args.model)
    print(markdown(curves))
    if args.chart:
        chart(curves, args.chart, args.x)
    if args.json:
        args.json.write_text(json.dumps(curves, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
