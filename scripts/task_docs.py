"""Write docs/TASKS.md from the tasks' TOML files: per task a picture of its scene (the front camera after a
reset), its variations, instructions, held-out paraphrases, success condition (from its environment's
docstring) and the expert's and the oracle's success as `benchmarks/oracle_bench.py --json` measured them.

    python scripts/task_docs.py [--tasks a,b | --task-set rlbench18] [--results oracle.json ...]
                                [--development runs.json] [--out docs/TASKS.md] [--images docs/img/tasks] [--seed 0]

--development adds what was measured while a task was built (benchmarks/results/rlbench18_cpu/
development_runs.json), labelled as such, beside the oracle_bench results.
"""

import argparse
import inspect
import json
import os
import textwrap
from pathlib import Path

TASK_SETS = """## Task sets

`maniskill9`: eight ManiSkill 3 Panda tasks (insert_peg, plug_charger, lift_peg_upright, pick_cube, place_sphere,
pull_cube, push_cube, stack_cube) and stack_pyramid. `rlbench18` (rvt2-18): RLBench's 18 tasks (the set of PerAct,
RVT and RVT-2) rebuilt in ManiSkill from shapes and joints made in code, with RLBench's 249 variations. A task's
`[[variations]]` give its instruction's values; the seed lays out the scene and the variation changes only the
instruction and the success check, so the policy must read the instruction.

    rvt2 record --task-set rlbench18 --episodes 100 --workers 30   # episodes spread evenly over each task's variations
    rvt2 eval --checkpoint runs/x --task-set rlbench18 --paraphrases      # held-out phrasings; success per variation and phrasing
    rvt2 eval --checkpoint runs/x --task-set rlbench18 --first-phrasing   # each variation's first phrasing, as the paper evaluates

One pool of simulator processes records every task of the set (or of `--task a,b,c`): 30 workers rendering with
lavapipe recorded rvt2-18's 1,800 demos in 570 s on 32 cores of a 4 x H200 host (docs/BENCHMARKS.md, "Recording
cost"). On 50 seeds spread over the variations every rvt2-18 expert succeeds on at least 96% and its oracle (its
keyframes through `rvt2 eval`'s executor) on at least 94% (docs/BENCHMARKS.md, "rvt2-18"). `rvt2 eval` runs the
tasks in turns, so one stopped part way holds every task's first seeds, and `--resume` finishes it.

The runs on rvt2-18 are experiment files (`experiments/`, docs/RESULTS.md): `rvt2_18_via` (the headline: 100 demos
per task, the two colour tasks' experts stopping above the named target first, 6,000 steps at batch 192, 100
evaluation seeds per task in two ranges of 50 reported apart, and the held-out paraphrases), `rvt2_18` (the same
with RLBench's paths for those two experts), `rvt2_18_25demos`, and the two colour tasks alone (`rvt2_18_colour`,
`rvt2_18_colour_via`; `rvt2 record --expert TASK=module:function`); planned, each on `rvt2_18_via`'s experts and
renderer: `rvt2_18_via_10demos` and `rvt2_18_via_25demos`, `rvt_18` (RVT for the same training time),
`rvt2_18_unseen` (trained without the held-out variations of the four compositional tasks, evaluated on them) and
`rvt2_18_phrasings` (`rvt2 train --phrasings all`). `python -m benchmarks.results_table ... --paper
benchmarks/paper_rlbench18.toml#rvt2` sets a results table beside the paper's (RVT-2, RVT and PerAct, per task).

"""  # the task sets and the runs on them, before the table
IMAGE_SIZE = 192  # px: a small picture, enough to tell the objects and their colours apart


def success_condition(env_class) -> tuple[str, str]:
    """What a section says of success, and under which label. ManiSkill's docstrings list it under
    **Success Conditions:**; rvt2-18's environments say it in their class's docstring or, with the scene it
    is checked in, in their module's (after its first line)."""
    doc = inspect.cleandoc(env_class.__doc__ or "")
    if "**Success Conditions:**" in doc:
        section = doc.split("**Success Conditions:**", 1)[1].strip().split("\n\n", 1)[0]
        items = [" ".join(item.split()) for item in ("\n" + section).split("\n- ") if item.strip()]
        return "Success", "; ".join(items)
    if doc:
        return "Success", " ".join(doc.split())
    module = inspect.cleandoc(inspect.getmodule(env_class).__doc__ or "")
    if "\n\n" in module:
        return "The scene and its success", " ".join(module.split("\n\n", 1)[1].split())
    return "Success", "(the environment's docstring does not say)"


def save_picture(task, path: Path, seed: int):
    """Save the front camera's picture of the task's scene; returns the task's environment class."""
    from PIL import Image

    from rvt2cli.record.capture import capture_cameras
    from rvt2cli.record.scene import make_env, set_variation

    env = make_env(task, cameras=("front",), image_size=IMAGE_SIZE)
    try:
        set_variation(env, 0)
        env.reset(seed=seed)
        # a palette of 128 colours keeps the file small (a few kB) and the objects' colours apart
        Image.fromarray(capture_cameras(env)["front"].rgb).quantize(128).save(path, optimize=True)
        return type(env.unwrapped).__bases__[0]  # make_env's scene subclasses the task's environment
    finally:
        env.close()


def measured(results: list[dict]) -> dict[str, list[str]]:
    """Per task, one line per benchmark run that measured it."""
    out: dict[str, list[str]] = {}
    for result in results:
        m = result.get("machine", {})
        machine = f"{m.get('cores', '?')}-core {m.get('cpu', 'unknown CPU')}, Python {m.get('python', '?')}"
        for row in result["tasks"]:
            seeds = f"seeds {row['first_seed']}-{row['first_seed'] + row['seeds'] - 1}"
            line = f"expert {row['expert']:.0%}, oracle {row['oracle']:.0%} ({seeds}; {row.get('machine', machine)})"
            if len(row.get("expert_per_variation", {})) > 1:
                line += "; per variation (expert / oracle): " + ", ".join(
                    f"{v}: {row['expert_per_variation'][v]:.0%} / {row['oracle_per_variation'].get(v, 0):.0%}"
                    for v in row["expert_per_variation"])
            out.setdefault(row["task"], []).append(line)
    return out


def development(path: str | None) -> dict[str, list[str]]:
    """Per task, the line of a development-runs file (expert and oracle counts with their seeds)."""
    if not path:
        return {}
    runs = json.loads(Path(path).read_text())
    return {task: [f"while it was built: expert {r['expert']}, oracle {r['oracle']} ({runs['machine']}, {runs['date']})"]
            for task, r in runs["tasks"].items()}


def section(task, env_class, picture: str, success: list[str]) -> str:
    lines = [f"## {task.name}", "", f"![{task.name}]({picture})", "",
             f"Environment `{task.env_id}`, expert `{task.expert}`, {task.max_steps} control steps at most"
             + (f"; task sets: {', '.join(task.task_sets)}" if task.task_sets else "") + ".", "",
             "**{}:** {}".format(*success_condition(env_class)), ""]
    if task.variations:
        held = set(task.held_out_variations)
        lines += [f"**Variations ({task.num_variations}):**", "", "| variation | values | instruction (first template) |",
                  "|---|---|---|"]
        for v in range(task.num_variations):
            values = ", ".join(f"{k}={x}" for k, x in sorted(task.variation_values(v).items()))
            mark = " (held out)" if v in held else ""
            lines.append(f"| {v}{mark} | {values} | {task.instructions[0].format(**task.variation_values(v))} |")
        lines.append("")
    else:
        lines += ["**Variations:** one.", ""]
    lines += ["**Instructions** (templates):", ""] + [f"- {t}" for t in task.instructions] + [""]
    if task.paraphrases:
        lines += ["**Held-out paraphrases** (`rvt2 eval --paraphrases`; never in training):", ""]
        lines += [f"- {t}" for t in task.paraphrases] + [""]
    lines += ["**Measured:** " + ("; ".join(success) if success else "not yet (run `benchmarks/oracle_bench.py --json`)."), ""]
    return "\n".join(lines)


def main() -> None:
    from rvt2cli.tasks import all_tasks, tasks_of_set

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", help="comma-separated (default: every task)")
    parser.add_argument("--task-set")
    parser.add_argument("--results", nargs="*", default=[], help="JSON files of benchmarks/oracle_bench.py --json")
    parser.add_argument("--development", help="a JSON of expert and oracle counts measured while the tasks were built")
    parser.add_argument("--out", default="docs/TASKS.md")
    parser.add_argument("--images", default="docs/img/tasks")
    parser.add_argument("--seed", type=int, default=0, help="the seed of every picture's scene (variation 0)")
    args = parser.parse_args()
    names = args.tasks.split(",") if args.tasks else tasks_of_set(args.task_set) if args.task_set else list(all_tasks())
    results = measured([json.loads(Path(p).read_text()) for p in args.results])
    for task, lines in development(args.development).items():
        results.setdefault(task, []).extend(lines)
    out, images = Path(args.out), Path(args.images)
    images.mkdir(parents=True, exist_ok=True)
    tasks = [all_tasks()[n] for n in names]
    parts = [textwrap.dedent(f"""\
        # Tasks

        Written by `scripts/task_docs.py` from `tasks/*.toml`; do not edit by hand. Each picture is the front
        camera ({IMAGE_SIZE} px) after a reset with seed {args.seed}, in variation 0. A task with variations lays out
        the same scene for a seed in every variation: only the instruction and the success check differ.

        """) + TASK_SETS + "| task | environment | variations | task sets |\n|---|---|---|---|\n"]
    parts[0] += "\n".join(f"| [{t.name}](#{t.name}) | {t.env_id} | {t.num_variations} | {', '.join(t.task_sets) or '-'} |"
                          for t in tasks) + "\n"
    for task in tasks:
        picture = images / f"{task.name}.png"
        env_class = save_picture(task, picture, args.seed)
        parts.append(section(task, env_class, os.path.relpath(picture, out.parent),
                             results.get(task.name, [])))
        print(f"{task.name}: {picture}", flush=True)
    out.write_text("\n".join(parts))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
