"""Which target did the policy choose? On the tasks that push an object across the table to the target of
a named colour, the push's direction says which target the policy went for, whether or not the object ended
on it.

    rvt2 diagnose target-choice JOURNAL... [--source oracle] [--via] [--json FILE]

Each policy episode (or the oracle's: the expert's keyframes, which choose the named target every time) of
reach_and_drag or slide_block_to_color_target in the evaluation journals (`rvt2 eval`'s episodes.jsonl, or its
compressed copy) is rebuilt from its seed and variation, which lay out the scene as the
evaluation saw it. The push is the first move between two keyframes near the table (both under
`SWEEP_HEIGHT_M`) longer than `SWEEP_MIN_M`: the stick dragging the cube, or the closed fingers sliding the
block. The chosen target is the one whose direction from the object's start is nearest to the push's, where
that is within `CHOICE_TOLERANCE_DEG` (else the episode made no clear choice). Reported per task: how often
the chosen target is the named one, against chance (one in the number of targets), and the success of the
episodes that chose it.

`--via`: the policy learnt from experts that stop above the named target before the push (`expert_via_target`,
`experiments/rvt2_18_colour_via.toml`). Their stop is the keyframe two before the push's start (then come the
hover above the push's start and the descent onto it); the report also says how often the policy's stop was
nearest the named target and how often the push then went for the target it had stopped above.
"""

from dataclasses import dataclass

import numpy as np

from rvt2cli.errors import UserError
from rvt2cli.eval.journal import read_records
from rvt2cli.eval.report import wilson_interval
from rvt2cli.tasks import get_task

SWEEP_HEIGHT_M = 0.03      # both keyframes of the push this close to the table (the TCP's height)
SWEEP_MIN_M = 0.05         # and this far apart on the table
CHOICE_TOLERANCE_DEG = 20  # the targets lie 35 (reach_and_drag) and 90 (slide_block) degrees apart
STOP_MIN_HEIGHT_M = 0.08   # the via experts stop 0.10-0.12 m high (--via)
TASKS = ("reach_and_drag", "slide_block_to_color_target")


@dataclass(frozen=True)
class Layout:
    """Where the pushed object starts, where each target lies (xy, m), their colours and which of them the
    instruction names."""

    start: np.ndarray
    targets: list[np.ndarray]
    colours: list[str]
    named: int


def layout(task_name: str, scene) -> Layout:
    """The layout of a reset scene (`env.unwrapped`) of one of the two tasks."""
    xy = lambda actor: np.asarray(actor.pose.sp.p[:2], dtype=np.float64)  # noqa: E731
    if task_name == "reach_and_drag":
        return Layout(xy(scene.cube), [xy(s) for s in scene.squares], list(scene.square_colors), scene.target_square)
    if task_name == "slide_block_to_color_target":
        from rvt2cli.record.rlbench18.slide_block_to_color_target import COLORS

        return Layout(xy(scene.block), [xy(t) for t in scene.targets], list(COLORS), scene.variation)
    raise UserError(f"{task_name}: target_choice knows {' and '.join(TASKS)}")


def _sweep_start(targets: list[list[float]]) -> int | None:
    """The index of the keyframe target where the first sweep over the table starts, or None."""
    for i, (a, b) in enumerate(zip(targets, targets[1:])):
        if a[2] < SWEEP_HEIGHT_M and b[2] < SWEEP_HEIGHT_M and np.linalg.norm(np.subtract(b[:2], a[:2])) > SWEEP_MIN_M:
            return i
    return None


def push(targets: list[list[float]]) -> np.ndarray | None:
    """The first sweep over the table among an episode's keyframe targets (xy, m), or None."""
    i = _sweep_start(targets)
    return None if i is None else np.subtract(targets[i + 1][:2], targets[i][:2])


def via_stop(scene: Layout, targets: list[list[float]]) -> int | None:
    """The target nearest the stop the via experts make, the keyframe two before the push's start (see the
    module's docstring), or None where there is no push or that keyframe is lower than a stop."""
    start = _sweep_start(targets)
    if start is None or start < 2 or targets[start - 2][2] < STOP_MIN_HEIGHT_M:
        return None
    return int(np.argmin([np.linalg.norm(np.subtract(targets[start - 2][:2], t)) for t in scene.targets]))


def _bearing(v) -> float:
    """The direction of a vector on the table (rad)."""
    return float(np.arctan2(v[1], v[0]))


def chosen_target(scene: Layout, move: np.ndarray | None) -> int | None:
    """The target in the push's direction from the object's start, or None where no target is within the
    tolerance (or there was no push)."""
    if move is None:
        return None
    # the angle between the push and each target's direction, wrapped into [0, pi]
    off = [abs(np.angle(np.exp(1j * (_bearing(move) - _bearing(t - scene.start))))) for t in scene.targets]
    best = int(np.argmin(off))
    return best if np.degrees(off[best]) <= CHOICE_TOLERANCE_DEG else None


def episode_choices(envs: dict, records: list[dict], source: str = "policy", via: bool = False) -> list[dict]:
    """`envs`: each task's environment (`rvt2cli.record.scene.make_env`). One row per episode of `source` (policy
    or oracle) of the two tasks: its seed, variation, success, the targets' colours, the named and the chosen
    target (None: no clear choice), and with `via` the target of its stop (`via_stop`)."""
    from rvt2cli.record.scene import set_variation
    from rvt2cli.runtime import seed_everything

    rows = []
    for r in records:
        if r["source"] != source or r["task"] not in envs:
            continue
        task_env = envs[r["task"]]
        seed_everything(r["seed"])
        set_variation(task_env, r["variation"])
        task_env.reset(seed=r["seed"])
        scene = layout(r["task"], task_env.unwrapped)
        targets = [s["target"] for s in r["steps"]]
        rows.append({"task": r["task"], "seed": r["seed"], "variation": r["variation"], "success": bool(r["success"]),
                     "targets": len(scene.targets), "colours": scene.colours, "named": scene.named,
                     "chosen": chosen_target(scene, push(targets)),
                     "stopped_above": via_stop(scene, targets) if via else None})
    return rows


def summarise(rows: list[dict]) -> dict[str, dict]:
    out = {}
    for task in dict.fromkeys(r["task"] for r in rows):
        mine = [r for r in rows if r["task"] == task]
        clear = [r for r in mine if r["chosen"] is not None]
        named = [r for r in clear if r["chosen"] == r["named"]]
        low, high = wilson_interval(len(named), len(clear)) if clear else (0.0, 0.0)
        out[task] = {"episodes": len(mine), "clear_choices": len(clear), "named_chosen": len(named),
                     "named_chosen_interval": [low, high], "chance": 1.0 / mine[0]["targets"],
                     "success": sum(r["success"] for r in mine),
                     "success_when_named_chosen": sum(r["success"] for r in named)}
        stops = [r for r in mine if r["stopped_above"] is not None]
        out[task].update(stops=len(stops), stops_above_named=sum(r["stopped_above"] == r["named"] for r in stops),
                         pushes_after_stop=sum(r["chosen"] is not None for r in stops),
                         pushes_to_stop_target=sum(r["chosen"] == r["stopped_above"] for r in stops))
    return out


def report(journals, source: str = "policy", via: bool = False) -> dict:
    """The rows (`episode_choices`) and their summary per task (`summarise`) of the journals' episodes of `source`."""
    records = read_records(journals)
    present = [t for t in TASKS if any(r["task"] == t and r["source"] == source for r in records)]
    if not present:
        raise UserError(f"no {source} episode of {' or '.join(TASKS)} in {', '.join(map(str, journals))}; "
                        "give an evaluation of them")
    from rvt2cli.record.scene import make_env

    envs = {name: make_env(get_task(name), cameras=[]) for name in present}
    try:
        rows = episode_choices(envs, records, source, via)
    finally:
        for env in envs.values():
            env.close()
    return {"journals": [str(j) for j in journals], "source": source, "via": via, "summary": summarise(rows), "rows": rows}


def markdown(report: dict) -> str:
    lines = [f"which target the {report['source']}'s push went for", "",
             "| task | episodes | a clear choice | the named target chosen | chance | success | success when the named target was chosen |",
             "|---|---|---|---|---|---|---|"]
    for task, s in report["summary"].items():
        low, high = s["named_chosen_interval"]
        share = s["named_chosen"] / s["clear_choices"] if s["clear_choices"] else 0.0
        lines.append(f"| {task} | {s['episodes']} | {s['clear_choices']} | {s['named_chosen']} ({share:.0%}; {low:.0%}-{high:.0%}) "
                     f"| {s['chance']:.0%} | {s['success']} | {s['success_when_named_chosen']} |")
    if report["via"]:
        lines += ["", "The stop above a target before the push (the keyframe two before it):", "",
                  "| task | episodes with a stop | nearest the named target | a clear push after it | the push went for the target of the stop |",
                  "|---|---|---|---|---|"]
        for task, s in report["summary"].items():
            lines.append(f"| {task} | {s['stops']} | {s['stops_above_named']} | {s['pushes_after_stop']} | {s['pushes_to_stop_target']} |")
    return "\n".join(lines) + "\n"
