"""An experiment file (`experiments/*.toml`) turned into the `rvt2` commands that make its results.

An experiment file is data: the tasks, the demos per task and their seeds, the held-out demos, the
training options, steps, batch and training seeds, the evaluation's episodes and seeds, and optionally
the renderer every phase uses (`renderer = "lavapipe"` or "nvidia": RVT2_VULKAN in the commands'
environment). A file may start from another (`extends = "rvt2_18_onegpu"`) and give only its name and what it
changes, table by table (not the other's [published]). This module prints those commands (`--print`, the default) or runs them one after the
other (`--run`), each phase timed into OUT/phases.tsv. The phases, in order:

    record    the training demos of every task, annotated with keyframes as they are written (`rvt2 extract-keyframes
              --merge-refinements` afterwards where the file asks for `merge_refinements_mm`); with
              `hold_out_variations = true`, none of a task's held-out variations (`rvt2 record --hold-out-variations`)
    heldout   demos on seeds training never sees, scored offline
    train     one run per training seed (torchrun when --gpus > 1, the global batch kept); with --time-limit
              each training stops there with a checkpoint (`rvt2 train --time-limit`), and the phase run again
              (here, or on another machine with the run folder restored) resumes a run stopped so
    eval      each run closed loop on the evaluation seeds (resumed where an earlier run was interrupted):
              with `ranges = N`, N disjoint ranges of seeds, one report each (evals/seed0_from10000, ...);
              each `[eval.extra.NAME]` table is one more evaluation with its own options (evals/seed0_NAME).
              The phase's evaluations run at the same time, sharing --workers in proportion to the
              episodes each has left (an interrupted one resumes): their workers start once, together,
              and no core waits for another evaluation's last episodes. `--evaluations main` runs the
              evaluation seeds' ranges alone (a machine short of time), the extra ones later by their names
    offline   each run's precision in millimetres on the held-out demos
    oracle    the expert's own keyframes through the same executor, on the evaluation seeds

With `alongside_training = ["heldout", "oracle"]` those phases, which need only the cores, run while the GPU
trains (one machine: its cores are idle while samples on the GPU train), with two workers fewer, left to the
training; the eval phase waits for both.

    python -m benchmarks.experiment experiments/rvt2_25demos.toml                    # print every command
    python -m benchmarks.experiment rvt2_10demos --run --phase train,eval --gpus 2   # some phases, 2 GPUs
    python -m benchmarks.experiment rvt2_25demos --run --out data/h --rvt2 "python3 -m rvt2cli"
    python -m benchmarks.experiment rvt2_18_onegpu --run --steps 3000 --eval-seeds 20000-20049   # a schedule, on validation seeds
    python -m benchmarks.experiment rvt2_18_via --run --renderer nvidia --gpus 2 --eval-seeds 20000-20049 \
        --eval-steps 1500,3000,4500 --curve-episodes 25   # a success-vs-steps curve: one schedule's checkpoints,
                                                          # on validation seeds (the earlier ones on 25 a task)

The offline-GPU kit runs the same phases (`scripts/offline-gpu-host/gpu_onebox.sh experiment FILE PHASES`).
"""

import argparse
import itertools
import os
import shlex
import subprocess
import sys
import threading
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

from rvt2cli.cli.args import names
from rvt2cli.cli.train import OUT_OF_TIME
from rvt2cli.errors import UserError
from rvt2cli.eval.journal import NAME as JOURNAL, read_journal
from rvt2cli.runtime import render_threads
from rvt2cli.tasks import get_task

REPOSITORY = Path(__file__).resolve().parent.parent
EXPERIMENTS = REPOSITORY / "experiments"
PHASES = ("record", "heldout", "train", "eval", "offline", "oracle")
CONCURRENT_PHASES = {"eval"}  # its commands run at the same time (`commands` shares the workers among them)

# The keys an experiment file may have, per table; anything else is a typo the user should hear about.
SCHEMA = {
    "": {"name", "summary", "renderer", "tasks", "alongside_training", "record", "heldout", "train", "eval", "oracle",
         "published", "extends"},
    "record": {"demos_per_task", "first_seed", "merge_refinements_mm", "hold_out_variations", "experts"},
    "heldout": {"tasks", "demos_per_task", "first_seed"},
    "train": {"config", "seeds", "steps", "batch_size", "options"},
    "eval": {"episodes_per_task", "first_seed", "options", "ranges", "extra"},
    "eval.extra.*": {"episodes_per_task", "first_seed", "options"},
    "oracle": {"episodes_per_task", "first_seed"},
    "published": {"results", "raw", "machine", "notes"},
}
RENDERERS = ("auto", "nvidia", "lavapipe")  # RVT2_VULKAN's choices: every phase renders with the file's
ALONGSIDE = ("heldout", "oracle")  # the phases that may run while the GPU trains: they need no trained model
CORES_FOR_TRAINING = 2  # the workers a phase alongside training leaves to the training's own processes
REQUIRED = {"record": "demos_per_task", "heldout": "demos_per_task", "train": "steps", "eval": "episodes_per_task",
            "oracle": "episodes_per_task"}


@dataclass(frozen=True)
class Settings:
    """What depends on the machine, not on the experiment."""

    out: Path
    rvt2: tuple[str, ...] = ("rvt2",)
    torchrun: tuple[str, ...] = ("torchrun",)
    workers: int = 1
    gpus: int = 1
    device: str = "cuda"
    training_seeds: tuple[int, ...] | None = None  # None: the experiment's
    evaluations: tuple[str, ...] | None = None  # the eval phase's evaluations by name ("main", extras'); None: all
    steps: int | None = None  # None: the experiment's; else another schedule's length (warmup as the file gives it)
    eval_seeds: tuple[int, int] | None = None  # (first, last): one evaluation on these seeds instead of the file's
    eval_steps: tuple[int, ...] = ()  # earlier checkpoints of each run evaluated as its last is (a success-vs-steps curve)
    curve_episodes: int | None = None  # episodes per task at those earlier checkpoints (their first seeds); None: as the last
    time_limit: float | None = None  # minutes: each training stops there with a checkpoint, resumed when the phase runs again


def resolve(name: str) -> Path:
    """An experiment file's path from a path or a bare name in experiments/ (`rvt2_25demos`)."""
    path = Path(name)
    if not path.exists() and path.suffix != ".toml":
        path = EXPERIMENTS / f"{name}.toml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in EXPERIMENTS.glob("*.toml")))
        raise UserError(f"{name}: no such experiment file; give a path or one of: {known}")
    return path


def merged(base: dict, changes: dict) -> dict:
    """`base` with `changes` laid over it, table by table: a key changes, every other key stays."""
    return base | {k: merged(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
                   for k, v in changes.items()}


def load(path: Path, _extending: tuple[Path, ...] = ()) -> dict:
    """The experiment file, its keys checked against SCHEMA and its tasks against tasks/*.toml."""
    from rvt2cli.tasks import all_tasks

    try:
        experiment = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise UserError(f"{path}: not valid TOML ({e}); fix the file") from None
    if "extends" in experiment:  # another experiment file with some of its keys changed
        base_name = experiment.pop("extends")
        if not isinstance(base_name, str):
            raise UserError(f"{path}: extends = {base_name!r}; give another experiment file's name, e.g. \"rvt2_18_onegpu\"")
        if "name" not in experiment:
            raise UserError(f"{path}: extends {base_name} but gives no 'name' of its own; add one (its runs' folder)")
        base_path = resolve(base_name)
        if base_path.resolve() in _extending:
            raise UserError(f"{path}: extends {base_name}, which extends it again; break the circle")
        base = load(base_path, (*_extending, path.resolve()))
        base = {k: v for k, v in base.items() if k != "published"}  # its results are not this file's
        experiment = merged(base, experiment)
    sections = {table: experiment if table == "" else experiment.get(table, {}) for table in SCHEMA if "*" not in table}
    sections |= {f"eval.extra.{name}": extra for name, extra in experiment.get("eval", {}).get("extra", {}).items()}
    for table, section in sections.items():
        allowed = SCHEMA.get(table) or SCHEMA["eval.extra.*"]
        unknown = sorted(set(section) - allowed)
        if unknown:
            where = f"[{table}]" if table else "the top level"
            raise UserError(f"{path}: unknown key {unknown[0]!r} in {where}; known: {', '.join(sorted(allowed))}")
    for name, extra in experiment.get("eval", {}).get("extra", {}).items():
        if "episodes_per_task" not in extra:
            raise UserError(f"{path}: [eval.extra.{name}] has no 'episodes_per_task'; add it")
    ranges = experiment.get("eval", {}).get("ranges", 1)
    episodes = experiment.get("eval", {}).get("episodes_per_task", 0)
    if not isinstance(ranges, int) or ranges < 1 or episodes % ranges:
        raise UserError(f"{path}: [eval] ranges = {ranges} does not divide episodes_per_task = {episodes} "
                        "into whole ranges; give a number of ranges that divides it")
    if not isinstance(experiment.get("record", {}).get("hold_out_variations", False), bool):
        raise UserError(f"{path}: [record] hold_out_variations takes true or false")
    experts = experiment.get("record", {}).get("experts", {})
    if not isinstance(experts, dict) or not all(isinstance(v, str) and ":" in v for v in experts.values()):
        raise UserError(f"{path}: [record] experts takes task = \"module:function\" pairs, e.g. "
                        "{ reach_and_drag = \"rvt2cli.record.rlbench18.reach_and_drag:expert_via_target\" }")
    if set(experts) - set(experiment.get("tasks", [])):
        raise UserError(f"{path}: [record] experts names {sorted(set(experts) - set(experiment['tasks']))[0]!r}, "
                        "which is not among the file's tasks")
    alongside = experiment.get("alongside_training", [])
    if not isinstance(alongside, list) or set(alongside) - set(ALONGSIDE):
        raise UserError(f"{path}: alongside_training = {alongside!r}; give a list of some of {', '.join(ALONGSIDE)}")
    if experiment.get("renderer", "auto") not in RENDERERS:
        raise UserError(f"{path}: renderer = {experiment['renderer']!r}; choose one of {', '.join(RENDERERS)}")
    for required in ("name", "tasks", "record", "train", "eval"):
        if required not in experiment:
            raise UserError(f"{path}: no {required!r}; every experiment file gives name, tasks, [record], [train] and [eval]")
    for table, key in REQUIRED.items():
        if table in experiment and key not in experiment[table]:
            raise UserError(f"{path}: [{table}] has no {key!r}; add it")
    known = all_tasks()
    for task in experiment["tasks"] + experiment.get("heldout", {}).get("tasks", []):
        if task not in known:
            raise UserError(f"{path}: unknown task {task!r}; known: {', '.join(sorted(known))}")
    return experiment


def options(table: dict) -> list[str]:
    """A TOML table of command-line options as arguments: `aim-held = true` -> --aim-held,
    `steps = 10` -> --steps 10, a table -> --task-weights insert_peg=3,plug_charger=3."""
    argv = []
    for key, value in table.items():
        if value is True:
            argv.append(f"--{key}")
        elif isinstance(value, dict):
            argv += [f"--{key}", ",".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in value.items())]
        elif value is not False:
            argv += [f"--{key}", str(value)]
    return argv


MAIN_EVALUATION = "main"  # the evaluation seeds' ranges; the extra evaluations go by their [eval.extra.NAME]


def evaluations(evaluate: dict, chosen: tuple[str, ...] | None = None,
                named_by_seed: bool = False) -> list[tuple[str, int, int, dict]]:
    """(folder suffix, episodes per task, first seed, options) of each evaluation of a trained run: the
    evaluation seeds, split into `ranges` disjoint ranges reported apart ("main"), then each
    [eval.extra.NAME]; only those `chosen` names, where given. A single range's folder is named by its first
    seed only with `named_by_seed` (seeds given on the command line)."""
    episodes, first_seed, ranges = evaluate["episodes_per_task"], evaluate.get("first_seed", 10000), evaluate.get("ranges", 1)
    extras = evaluate.get("extra", {})
    unknown = [name for name in chosen or () if name != MAIN_EVALUATION and name not in extras]
    if unknown or chosen == ():
        raise UserError(f"--evaluations {','.join(chosen)}: no evaluation {', '.join(unknown) or 'named'}; "
                        f"this experiment has {', '.join([MAIN_EVALUATION, *extras])}")
    runs = []
    if chosen is None or MAIN_EVALUATION in chosen:
        size = episodes // ranges
        runs = [(f"_from{first_seed + k * size}" if ranges > 1 or named_by_seed else "", size, first_seed + k * size,
                 evaluate.get("options", {})) for k in range(ranges)]
    for name, extra in extras.items():
        if chosen is None or name in chosen:
            runs.append((f"_{name}", extra["episodes_per_task"], extra.get("first_seed", first_seed),
                         {**evaluate.get("options", {}), **extra.get("options", {})}))
    return runs


def tasks_evaluated(tasks: list[str], options: dict) -> int:
    """How many tasks an evaluation with these options runs episodes of: options' `tasks` (as `rvt2 eval --tasks`
    reads it), and of those only the tasks with a variation to spread them over (`--variations held-out` leaves
    out a task without a held-out split, as `rvt2 eval` does)."""
    chosen = names(str(options["tasks"])) if "tasks" in options else tasks
    which = str(options.get("variations", "all"))
    return sum(1 for task in chosen if get_task(task).variation_choices(which))


def share_workers(workers: int, episodes: list[int]) -> list[int]:
    """`workers` split among evaluations in proportion to their episodes (largest remainders; each at least one)."""
    exact = [workers * e / sum(episodes) for e in episodes]
    shares = [int(x) for x in exact]
    for i in sorted(range(len(exact)), key=lambda i: shares[i] - exact[i])[:workers - sum(shares)]:
        shares[i] += 1
    return [max(1, share) for share in shares]


def episodes_left(folder: Path, episodes: int) -> int:
    """The episodes an evaluation into `folder` still has to run: those its journal lacks (at least one, so
    that a finished evaluation's command still gets a worker to write its report)."""
    journal = folder / JOURNAL
    return max(1, episodes - len(read_journal(journal)[1])) if journal.exists() else episodes


def beside_training(experiment: dict, phases) -> tuple[str, ...]:
    """The file's `alongside_training` phases where these phases train; none where they do not."""
    return tuple(experiment.get("alongside_training", [])) if "train" in phases else ()


def saved_steps(train: dict, settings: Settings) -> tuple[int, ...]:
    """settings.eval_steps, each checked to be a checkpoint the training keeps: a multiple of its save-every
    (`rvt2 train --save-every`, 1000 unless the file says) short of its last step."""
    steps, every = settings.steps or train["steps"], int(train.get("options", {}).get("save-every", 1000))
    wrong = [step for step in settings.eval_steps if step % every or not 0 < step < steps]
    if wrong:
        raise UserError(f"--eval-steps {','.join(map(str, wrong))}: the training keeps a checkpoint every {every} steps "
                        f"before its last ({steps}); give some of {','.join(map(str, range(every, steps, every))) or 'none'}")
    return settings.eval_steps


def commands(experiment: dict, settings: Settings, phases=PHASES) -> list[tuple[str, list[str]]]:
    """(phase, argv) for every command of these phases, in the order they run."""
    rvt2, out = list(settings.rvt2), settings.out
    alongside = beside_training(experiment, phases)
    record, heldout, train, evaluate = (experiment.get(k, {}) for k in ("record", "heldout", "train", "eval"))
    if settings.eval_seeds:  # e.g. validation seeds that choose a schedule: one range, none of the extra evaluations
        first, last = settings.eval_seeds
        evaluate = {"episodes_per_task": last - first + 1, "first_seed": first, "options": evaluate.get("options", {})}
    merge = ["--merge-refinements", str(record["merge_refinements_mm"])] if record.get("merge_refinements_mm") else []
    seeds = settings.training_seeds if settings.training_seeds is not None else tuple(train.get("seeds", [0]))
    batch = int(train.get("batch_size", 24))
    if batch % settings.gpus:
        raise UserError(f"--gpus {settings.gpus} does not divide the global batch {batch} of {experiment['name']}; "
                        "give a number of GPUs that divides it")
    launch = rvt2 if settings.gpus == 1 else [*settings.torchrun, "--standalone", "--nproc-per-node", str(settings.gpus), "-m", "rvt2cli"]
    run = []

    def workers_of(phase) -> str:
        return str(max(1, settings.workers - CORES_FOR_TRAINING) if phase in alongside else settings.workers)

    def demos(phase, folder, tasks, episodes, first_seed, extra=()):  # one command: its workers serve every task
        # held-out demos come from the same experts as the training demos
        experts = [a for task, spec in record.get("experts", {}).items() if task in tasks for a in ("--expert", f"{task}={spec}")]
        run.append((phase, rvt2 + ["record", "--task", ",".join(tasks), "--episodes", str(episodes), "--seed", str(first_seed),
                                   "--workers", workers_of(phase), "--out", str(out / folder), "--no-progress", *experts, *extra]))
        if merge:   # `rvt2 record` annotated them with the default rule; this one merges re-aimings
            run.append((phase, rvt2 + ["extract-keyframes", str(out / folder)] + merge))

    for phase in phases:
        if phase == "record":
            # the training demos only: held-out demos are scored offline, on every variation
            demos(phase, "demos", experiment["tasks"], record["demos_per_task"], record.get("first_seed", 0),
                  ["--hold-out-variations"] if record.get("hold_out_variations") else [])
        elif phase == "heldout" and heldout:
            demos(phase, "heldout", heldout.get("tasks", experiment["tasks"]), heldout["demos_per_task"],
                  heldout.get("first_seed", 30000))
        elif phase == "train":
            from rvt2cli.train.run_folder import stopped_at_time_limit

            limit = ["--time-limit", f"{settings.time_limit:g}"] if settings.time_limit else []
            for seed in seeds:
                run_dir = out / "runs" / f"seed{seed}"
                resume = ["--resume"] if stopped_at_time_limit(run_dir) else []
                run.append((phase, launch + ["train", "--data", str(out / "demos"), "--out", str(run_dir),
                                             "--config", train.get("config", "rvt2"), "--seed", str(seed),
                                             "--steps", str(settings.steps or train["steps"]), "--batch-size", str(batch // settings.gpus)]
                            + options(train.get("options", {})) + limit + resume + ["--no-progress"]))
        elif phase == "eval":
            each = evaluations(evaluate, settings.evaluations, named_by_seed=settings.eval_seeds is not None)

            def fewer(episodes, step):  # an earlier checkpoint's evaluation may take only the first seeds of each task
                return episodes if step is None or settings.curve_episodes is None else min(episodes, settings.curve_episodes)
            from rvt2cli.train.checkpoint import checkpoint_folder

            # the last checkpoint (the run folder) first, then each earlier one asked for: (step or None, folder suffix)
            steps = [(None, "")] + [(step, f"_step{step}") for step in saved_steps(train, settings)]
            runs = [(seed, name + suffix, fewer(episodes, step), *rest, step)
                    for seed in seeds for name, episodes, *rest in each for step, suffix in steps]
            folders = [out / "evals" / f"seed{seed}{name}" for seed, name, *_ in runs]
            tasks_of = [tasks_evaluated(experiment["tasks"], opts) for *_, opts, _ in runs]
            shares = share_workers(settings.workers, [episodes_left(folder, episodes * count)
                                                      for folder, (_, _, episodes, *_), count in zip(folders, runs, tasks_of)])
            for (seed, name, episodes, first_seed, extra_options, step), folder, share in zip(runs, folders, shares):
                resume = ["--resume"] if (folder / JOURNAL).exists() else []  # an interrupted evaluation
                run_dir = out / "runs" / f"seed{seed}"
                checkpoint = run_dir if step is None else checkpoint_folder(run_dir, step)
                run.append((phase, rvt2 + ["eval", "--checkpoint", str(checkpoint),
                                           "--episodes", str(episodes), "--seed", str(first_seed), "--workers", str(share),
                                           "--device", settings.device, "--out", str(folder)]
                            + options(extra_options) + resume + ["--no-progress"]))
        elif phase == "offline" and heldout:
            for seed in seeds:
                run.append((phase, rvt2 + ["eval", "--checkpoint", str(out / "runs" / f"seed{seed}"),
                                           "--offline", str(out / "heldout"), "--device", settings.device,
                                           "--out", str(out / "offline" / f"seed{seed}"), "--no-progress"]))
        elif phase == "oracle" and "oracle" in experiment:
            oracle = experiment["oracle"]
            run.append((phase, rvt2 + ["eval", "--oracle", "--tasks", ",".join(experiment["tasks"]),
                                       "--episodes", str(oracle["episodes_per_task"]),
                                       "--seed", str(oracle.get("first_seed", 10000)), "--workers", workers_of(phase),
                                       "--out", str(out / "oracle"), "--no-progress"]))
    return run


def environment(experiment: dict, workers: int) -> dict[str, str]:
    """What the commands' environment gains: the Vulkan driver of `renderer`, where the file names one.
    Demos and evaluations must share a renderer (docs/RESULTS.md, "Renderer"), so the file fixes it.
    And lavapipe's threads per simulator, counted over all `workers`: the evaluations that run together
    would each count only their share (30 of 60 workers on 64 cores: 2 threads each, 120 in all).
    A limit set in the caller's environment is kept."""
    renderer = experiment.get("renderer", "auto")
    gained = {} if renderer == "auto" else {"RVT2_VULKAN": renderer}
    return gained | {k: v for k, v in render_threads(workers).items() if k not in os.environ}


def runs_together(phase: str, argvs: list[list[str]]) -> bool:
    return phase in CONCURRENT_PHASES and len(argvs) > 1


def execute(run: list[tuple[str, list[str]]], out: Path, extra_environment: dict[str, str] | None = None,
            alongside: tuple[str, ...] = ()) -> int:
    """Phase by phase, stopping at the first command that fails; each phase's seconds into out/phases.tsv.
    A phase's commands run in turn, those of a phase in CONCURRENT_PHASES all at once. The phases named in
    `alongside` start with the train phase, in their own thread, and the train phase ends when they end."""
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, **(extra_environment or {})}
    phases = [(phase, [argv for _, argv in group]) for phase, group in itertools.groupby(run, key=lambda command: command[0])]
    beside = [(phase, argvs) for phase, argvs in phases if phase in alongside] if any(p == "train" for p, _ in phases) else []
    for phase, argvs in phases:
        if (phase, argvs) in beside:
            continue
        if phase != "train" or not beside:
            code = run_phase(phase, argvs, out, env)
        else:
            codes = []
            thread = threading.Thread(target=lambda: codes.append(run_phases(beside, out, env)))
            thread.start()
            code = run_phase(phase, argvs, out, env)
            thread.join()
            code = code or (codes[0] if codes else 1)   # no code: the thread itself failed (its error printed)
        if code:
            return code
    return 0


def run_phases(phases: list[tuple[str, list[list[str]]]], out: Path, env: dict[str, str]) -> int:
    for phase, argvs in phases:
        if code := run_phase(phase, argvs, out, env):
            return code
    return 0


def run_phase(phase: str, argvs: list[list[str]], out: Path, env: dict[str, str]) -> int:
    """One phase's commands (in turn, or all at once in CONCURRENT_PHASES); its seconds into out/phases.tsv."""
    started = time.monotonic()
    together = runs_together(phase, argvs)
    print(f"== {phase}" + (f" ({len(argvs)} commands at once)" if together else ""), flush=True)
    for batch in [argvs] if together else [[argv] for argv in argvs]:
        processes = []
        for argv in batch:
            print("$ " + shlex.join(argv), flush=True)
            try:
                processes.append((argv, subprocess.Popen(argv, env=env)))
            except FileNotFoundError:
                print(f"experiment: error: {argv[0]}: not found; run `make setup` and `source .venv/bin/activate`, "
                      "or name the command with --rvt2", file=sys.stderr)
                for _, process in processes:
                    process.wait()
                return 2
        failed = [(argv, code) for argv, process in processes if (code := process.wait())]
        if phase == "train" and all(code == OUT_OF_TIME for _, code in failed) and stopped(batch):
            print(f"experiment: the training stopped at its --time-limit with a checkpoint ({shlex.join(batch[0])}); "
                  "run the train phase again to resume it, here or on another machine with its run folder restored",
                  file=sys.stderr)
            with open(out / "phases.tsv", "a") as f:
                f.write(f"train_stopped\t{time.monotonic() - started:.0f}\n")
            return OUT_OF_TIME
        if failed:  # the others ran to their end: an interrupted evaluation resumes from its journal
            argv, code = failed[0]
            print(f"experiment: {phase} failed (exit code {code}): {shlex.join(argv)}", file=sys.stderr)
            return code
    with open(out / "phases.tsv", "a") as f:
        f.write(f"{phase}\t{time.monotonic() - started:.0f}\n")
    return 0


def stopped(train_commands: list[list[str]]) -> bool:
    """Whether one of these `rvt2 train` commands stopped at its --time-limit (its --out's run.json says so)."""
    from rvt2cli.train.run_folder import stopped_at_time_limit

    return any("--out" in argv and stopped_at_time_limit(Path(argv[argv.index("--out") + 1])) for argv in train_commands)


def parse_phases(text: str) -> tuple[str, ...]:
    phases = PHASES if text == "all" else tuple(p for p in text.split(",") if p)
    unknown = [p for p in phases if p not in PHASES]
    if unknown or not phases:
        raise UserError(f"--phase {text}: give 'all' or some of {','.join(PHASES)}, comma-separated")
    return phases


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.experiment",
                                     description="Print or run the rvt2 commands of an experiment file (experiments/*.toml).")
    parser.add_argument("experiment", help="an experiment file, or its name in experiments/ (e.g. rvt2_25demos)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--print", dest="run", action="store_false", help="print the commands (default)")
    mode.add_argument("--run", action="store_true", help="run them, each phase timed into OUT/phases.tsv")
    parser.set_defaults(run=False)
    parser.add_argument("--phase", default="all", help=f"'all' (default) or some of {','.join(PHASES)}, in that order")
    parser.add_argument("--out", help="the experiment's folder: demos, runs, evaluations (default data/experiments/NAME)")
    parser.add_argument("--workers", type=int, default=max(1, (os.cpu_count() or 1) - 2),
                        help="simulator processes (default: the cores less two, which feed the GPU)")
    parser.add_argument("--gpus", type=int, default=1, help="GPUs to train on through torchrun, the global batch kept (default 1)")
    parser.add_argument("--device", default="cuda", help="the policy's device in evaluation (default cuda)")
    parser.add_argument("--training-seeds", help="comma-separated training seeds instead of the file's (e.g. 0)")
    parser.add_argument("--evaluations", help="the eval phase's evaluations to run, comma-separated: 'main' (the "
                        "evaluation seeds' ranges) and [eval.extra.NAME]'s names (default: all)")
    parser.add_argument("--steps", type=int, help="train this many steps instead of the file's (another schedule; the "
                        "default folder becomes data/experiments/NAME_STEPSsteps)")
    parser.add_argument("--eval-seeds", metavar="FIRST-LAST", help="evaluate on these seeds alone, e.g. validation seeds "
                        "20000-20049 that choose a schedule (one range, no extra evaluations; evals/seedN_fromFIRST)")
    parser.add_argument("--eval-steps", metavar="STEP,...", help="also evaluate these earlier checkpoints of each run "
                        "(multiples of the training's save-every), each as the last one is: a success-vs-steps curve "
                        "(evals/seedN_fromFIRST_stepSTEP)")
    parser.add_argument("--curve-episodes", type=int, metavar="N", help="with --eval-steps: evaluate the earlier "
                        "checkpoints on the first N seeds of each task only (the last one on all), so that a curve "
                        "fits the machine's time")
    parser.add_argument("--time-limit", type=float, metavar="MINUTES",
                        help="each training saves a checkpoint and stops after this many minutes (a machine's time; "
                             "exit code 75); the train phase run again resumes it")
    parser.add_argument("--renderer", choices=RENDERERS, help="every phase renders with this Vulkan driver instead of "
                        "the file's (e.g. nvidia where the file's lavapipe would take too long; demos and evaluations "
                        "still share it, and the default folder gains _RENDERER)")
    parser.add_argument("--rvt2", default="rvt2", help="the command that runs rvt2 (default rvt2; e.g. 'python3 -m rvt2cli')")
    parser.add_argument("--torchrun", default="torchrun",
                        help="the command that launches training on several GPUs (default torchrun)")
    args = parser.parse_args(argv)
    try:
        experiment = load(resolve(args.experiment))
        if args.workers < 1 or args.gpus < 1:
            raise UserError("--workers and --gpus take a whole number of at least 1")
        seeds = None
        if args.training_seeds:
            try:
                seeds = tuple(int(s) for s in args.training_seeds.split(","))
            except ValueError:
                raise UserError(f"--training-seeds {args.training_seeds}: give whole numbers, comma-separated") from None
        if args.steps is not None and args.steps < 1:
            raise UserError(f"--steps {args.steps}: give a whole number of at least 1")
        eval_seeds = None
        if args.eval_seeds:
            first, _, last = args.eval_seeds.partition("-")
            if not (first.isdigit() and last.isdigit() and int(first) <= int(last)):
                raise UserError(f"--eval-seeds {args.eval_seeds}: give FIRST-LAST, e.g. 20000-20049")
            eval_seeds = (int(first), int(last))
        try:
            eval_steps = tuple(int(s) for s in args.eval_steps.split(",")) if args.eval_steps else ()
        except ValueError:
            raise UserError(f"--eval-steps {args.eval_steps}: give whole numbers, comma-separated, e.g. 2000,4000") from None
        if args.curve_episodes is not None and (args.curve_episodes < 1 or not eval_steps):
            raise UserError(f"--curve-episodes {args.curve_episodes}: give a whole number of at least 1, with --eval-steps")
        if args.time_limit is not None and not args.time_limit > 0:
            raise UserError(f"--time-limit {args.time_limit:g}: give the minutes a training may take, more than 0")
        if args.renderer and args.renderer != experiment.get("renderer", "auto"):
            experiment = {**experiment, "renderer": args.renderer, "name": f"{experiment['name']}_{args.renderer}"}
        name = experiment["name"] + (f"_{args.steps}steps" if args.steps else "")
        out = Path(args.out or f"data/experiments/{name}")
        settings = Settings(out=out, rvt2=tuple(shlex.split(args.rvt2)), torchrun=tuple(shlex.split(args.torchrun)),
                            workers=args.workers, gpus=args.gpus,
                            device=args.device, training_seeds=seeds, steps=args.steps, eval_seeds=eval_seeds,
                            eval_steps=eval_steps, curve_episodes=args.curve_episodes, time_limit=args.time_limit,
                            evaluations=tuple(n for n in args.evaluations.split(",") if n) if args.evaluations else None)
        phases = parse_phases(args.phase)
        run = commands(experiment, settings, phases)
        alongside = beside_training(experiment, phases)
    except UserError as e:
        print(f"experiment: error: {e}", file=sys.stderr)
        return e.exit_code
    if args.run:
        return execute(run, out, environment(experiment, args.workers), alongside)
    for name, value in environment(experiment, args.workers).items():
        print(f"export {name}={value}")
    for phase, group in itertools.groupby(run, key=lambda command: command[0]):
        argvs = [argv for _, argv in group]
        together = runs_together(phase, argvs)
        print(f"# {phase}" + (" (run these at the same time: each has its share of the workers)" if together else "")
              + (" (while train runs)" if phase in alongside else ""))
        for argv in argvs:
            print(shlex.join(argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
