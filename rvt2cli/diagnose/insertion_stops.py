"""Where a policy's first insertion leaves the held object when it is pushed straight, and which of those
the executor's insertion search brings in (insert_peg, and plug_charger with --task).

For every episode of the task in a policy's `rvt2 eval` journal, the recorded keyframes are replayed
(`rvt2cli.eval.sources.ReplaySource`) by the executor without its search, the executor that recorded the
journal, up to the episode's first insertion: the first keyframe that ignores collisions with the object
in the closed gripper. Then the object is measured against its goal:
- insert_peg: the peg's head in the hole's frame (x along the hole's axis, into the box): how far across
  the axis it stopped, the larger of its two offsets (the peg and the hole are square, with 3 mm of
  clearance per side), and how far the peg slid back through the fingers during that push (the peg's
  centre in the TCP's frame, before against after);
- plug_charger: the charger in its goal's frame (x along the receptacle's axis) where the push starts,
  since pushed against the receptacle's face it pivots in the fingers: how far across the axis it is, the
  larger of its two offsets (0.5 mm of clearance), and its turn from the goal (the table's median is over
  every episode of a band, those that went in too); and the same after the push.
Whether it went in is measured for both. With `--searched`, an `rvt2 eval` folder of the same episodes
with the search (an `rvt2 eval --replay` of the journal, or the same checkpoint evaluated again: up to its
first insertion an episode is the same), each episode is also marked by whether it succeeded there.

    rvt2 diagnose insertion-stops JOURNAL [--task plug_charger] [--searched EVAL_DIR] [--workers 2] [--json out.json]
"""

from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rvt2cli.errors import UserError
from rvt2cli.eval.journal import NAME, read_journal

# across the axis: within the clearance, then wider and wider
BANDS_MM = {"insert_peg": (3.0, 5.0, 10.0, 20.0), "plug_charger": (0.5, 1.0, 2.0, 5.0)}


def first_insertion(steps: list[dict]) -> int | None:
    """Index of an episode's first insertion keyframe (None: it never inserted)."""
    return next((i for i, s in enumerate(steps) if i > 0 and s["reached"] and s["ignore_collisions"]
                 and not s["gripper_open"] and steps[i - 1]["held"]), None)


_envs: dict = {}


def peg_in_hand_mm(env) -> float:
    """How far the peg's centre sits ahead of the TCP along the gripper's x axis (the peg's axis), mm."""
    from rvt2cli.record.scene import tcp_pose

    tcp = tcp_pose(env).astype(np.float64)
    peg = env.unwrapped.peg.pose.raw_pose[0].cpu().numpy().astype(np.float64)
    return 1000.0 * float(Rotation.from_quat(tcp[3:]).inv().apply(peg[:3] - tcp[:3])[0])


def first_insertion_stop(record: dict) -> dict:
    """Replays an episode to its first insertion, pushed straight: where the peg stopped and how it slid, or
    where the charger started and where it stopped (`after`)."""
    from rvt2cli.eval.rollout import run_episode
    from rvt2cli.eval.sources import ReplaySource
    from rvt2cli.record.scene import make_env
    from rvt2cli.tasks import get_task

    if record["task"] not in BANDS_MM:
        raise UserError(f"insertion-stops measures {', '.join(BANDS_MM)}, not {record['task']}")
    index = first_insertion(record["steps"])
    if index is None:
        return {"seed": record["seed"], "insertion": None}
    task = get_task(record["task"])
    env = _envs.setdefault(task.name, make_env(task))
    before = {}

    class Replay(ReplaySource):  # notes where the held object sits before the insertion
        def next(self, cloud, gripper_open, finger_positions, keyframes_done, retry=0):
            if keyframes_done == index:  # the arm stands where the insertion's push starts
                if task.name == "insert_peg":
                    before["peg_mm"] = peg_in_hand_mm(env)
                elif task.name == "plug_charger":
                    before.update(charger_at_goal(env))
            return super().next(cloud, gripper_open, finger_positions, keyframes_done, retry)

    outcome = run_episode(env, task, record["seed"], Replay([record]), record["instruction"],
                          keyframe_budget=index + 1, step_budget=record["step_budget"], search=False)
    stop = {"seed": record["seed"], "insertion": index, "went_in": outcome.success}
    if task.name == "insert_peg":
        head = 1000.0 * env.unwrapped.evaluate()["peg_head_pos_at_hole"][0].numpy().astype(float)
        return {**stop, "head_mm": head.round(2).tolist(), "across_mm": round(float(np.abs(head[1:]).max()), 2),
                "slid_back_mm": round(before["peg_mm"] - peg_in_hand_mm(env), 2)}
    return {**stop, **before, "after": charger_at_goal(env)}


def charger_at_goal(env) -> dict:
    """The charger in its goal's frame (x along the receptacle's axis): offset, mm; the larger offset across
    the axis, mm; and its turn from the goal, degrees."""
    scene = env.unwrapped
    offset = 1000.0 * (scene.goal_pose.inv() * scene.charger.pose).p[0].numpy().astype(float)
    return {"offset_mm": offset.round(2).tolist(), "across_mm": round(float(np.abs(offset[1:]).max()), 2),
            "turn_deg": round(float(np.degrees(scene.evaluate()["obj_to_goal_angle"][0])), 2)}


def _band(across: float, bands: tuple[float, ...]) -> str:
    edges = (0.0, *bands)
    for low, high in zip(edges, edges[1:]):
        if across <= high:
            return f"{low:g}-{high:g} mm"
    return f"> {bands[-1]:g} mm"


def _median(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def _journal(path: Path) -> list[dict]:
    try:
        return read_journal(path)[1]
    except OSError as error:
        raise UserError(f"{path}: cannot read it ({error.strerror}); give an evaluation's episodes.jsonl") from None


def report(journal, task: str = "insert_peg", searched=None, workers: int = 2) -> dict:
    """Every policy episode of `task` in the `journal` replayed to its first insertion (`first_insertion_stop`),
    gathered into bands of how far across the axis it stopped. `searched`: an `rvt2 eval` folder of the same
    episodes with the search, whose successes mark each stop."""
    journal = Path(journal)
    if task not in BANDS_MM:
        raise UserError(f"insertion-stops measures {', '.join(BANDS_MM)}, not {task}")
    if not journal.is_file():
        raise UserError(f"{journal}: no such evaluation journal (an episodes.jsonl)")
    records = [r for r in _journal(journal) if r["task"] == task and r["source"] == "policy"]
    if not records:
        raise UserError(f"{journal}: no {task} episodes of a policy; give an evaluation of {task}")
    successes = {}
    if searched:
        if not (Path(searched) / NAME).is_file():
            raise UserError(f"{Path(searched) / NAME}: no evaluation journal; give an `rvt2 eval --out` folder")
        successes = {r["seed"]: r["success"] for r in _journal(Path(searched) / NAME) if r["task"] == task}
    with ProcessPoolExecutor(workers) as pool:
        stops = list(pool.map(first_insertion_stop, records))
    for stop in stops:
        if stop["seed"] in successes:
            stop["searched_success"] = successes[stop["seed"]]
    inserted = [s for s in stops if s["insertion"] is not None]
    limits = BANDS_MM[task]
    peg = task == "insert_peg"
    rows = []
    for band in [_band(0.0, limits)] + [_band(b + 1e-9, limits) for b in limits]:
        mine = [s for s in inserted if _band(s["across_mm"], limits) == band]
        if peg:  # of the pegs that did not go in
            detail_key, detail = "slid_back_mm_median_not_in", _median([s["slid_back_mm"] for s in mine if not s["went_in"]])
        else:    # of every charger in the band
            detail_key, detail = "turn_deg_median", _median([s["turn_deg"] for s in mine])
        rows.append({"band": band, "episodes": len(mine), "went_in": sum(s["went_in"] for s in mine),
                     "searched_success": sum(s.get("searched_success", False) for s in mine) if searched else None,
                     detail_key: detail})
    return {"task": task, "journal": str(journal), "searched": str(searched or ""), "episodes": len(records),
            "with_insertion": len(inserted), "rows": rows, "stops": stops}


def markdown(report: dict) -> str:
    peg = report["task"] == "insert_peg"
    where = ("the peg's head after the first, pushed straight, across the hole's axis" if peg else
             "the charger before the first (where the push starts), across the receptacle's axis")
    last = "peg slid back in the fingers, median mm" if peg else "turn from the goal, median deg"
    lines = [f"{report['task']}, {report['episodes']} episodes, {report['with_insertion']} with an insertion; {where}:", "",
             f"| across the axis | episodes | went in | success with the search | {last} |", "|---|---|---|---|---|"]
    for row in report["rows"]:
        detail = row.get("slid_back_mm_median_not_in", row.get("turn_deg_median"))
        shown = "-" if detail is None else (f"{detail:.0f}" if peg else f"{detail:.1f}")
        found = "-" if row["searched_success"] is None else row["searched_success"]
        lines.append(f"| {row['band']} | {row['episodes']} | {row['went_in']} | {found} | {shown} |")
    return "\n".join(lines) + "\n"
