"""Where a policy's first insertion leaves insert_peg's peg when it is pushed straight, and which of those
pegs the executor's insertion search brings in.

For every insert_peg episode of a policy's `rvt2 eval` journal, the recorded keyframes are replayed
(`rvt2cli.eval.sources.ReplaySource`) by the executor without its search, the executor that recorded the
journal, up to the episode's first insertion: the first keyframe that ignores collisions with the peg in
the closed gripper. Then the peg's head is measured in the hole's frame (x along the hole's axis, into
the box): how far across the axis it stopped, the larger of its two offsets (the peg and the hole are
square, with 3 mm of clearance per side), whether it went in, and how far the peg slid back through the
fingers during that push (the peg's centre in the TCP's frame, before against after). With `--searched`, an `rvt2 eval` folder of the
same episodes with the search (an `rvt2 eval --replay` of the journal, or the same checkpoint evaluated
again: up to its first insertion an episode is the same), each episode is also marked by whether it
succeeded there.

    python -m benchmarks.insertion_stops JOURNAL [--searched EVAL_DIR] [--workers 2] [--json out.json]
"""

import argparse
import json
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks.inhand_bench import in_hand
from benchmarks.machine import describe
from rvt2cli.errors import UserError
from rvt2cli.eval.journal import NAME, read_journal

BANDS_MM = (3.0, 5.0, 10.0, 20.0)  # across the axis: within the clearance, then wider and wider


def first_insertion(steps: list[dict]) -> int | None:
    """Index of an episode's first insertion keyframe (None: it never inserted)."""
    return next((i for i, s in enumerate(steps) if i > 0 and s["reached"] and s["ignore_collisions"]
                 and not s["gripper_open"] and steps[i - 1]["held"]), None)


_envs: dict = {}


def peg_in_hand_mm(env) -> float:
    """How far the peg's centre sits ahead of the TCP along the gripper's x axis (the peg's axis), mm."""
    return 1000.0 * float(in_hand(env, "peg")[0][0])


def first_insertion_stop(record: dict) -> dict:
    """Replays an episode to its first insertion, pushed straight: where the peg stopped, and how it slid."""
    from rvt2cli.eval.rollout import run_episode
    from rvt2cli.eval.sources import ReplaySource
    from rvt2cli.record.scene import make_env
    from rvt2cli.tasks import get_task

    index = first_insertion(record["steps"])
    if index is None:
        return {"seed": record["seed"], "insertion": None}
    task = get_task("insert_peg")
    env = _envs.setdefault(task.name, make_env(task))
    before = {}

    class Replay(ReplaySource):  # notes where the peg sits in the hand before the insertion
        def next(self, cloud, gripper_open, finger_positions, keyframes_done, retry=0):
            if keyframes_done == index:
                before["peg_mm"] = peg_in_hand_mm(env)
            return super().next(cloud, gripper_open, finger_positions, keyframes_done, retry)

    outcome = run_episode(env, task, record["seed"], Replay([record]), record["instruction"],
                          keyframe_budget=index + 1, step_budget=record["step_budget"], search=False)
    head = 1000.0 * env.unwrapped.evaluate()["peg_head_pos_at_hole"][0].numpy().astype(float)
    return {"seed": record["seed"], "insertion": index, "went_in": outcome.success, "head_mm": head.round(2).tolist(),
            "across_mm": round(float(np.abs(head[1:]).max()), 2),
            "slid_back_mm": round(before["peg_mm"] - peg_in_hand_mm(env), 2)}


def _band(across: float) -> str:
    edges = (0.0, *BANDS_MM)
    for low, high in zip(edges, edges[1:]):
        if across <= high:
            return f"{low:g}-{high:g} mm"
    return f"> {BANDS_MM[-1]:g} mm"


def _journal(path: Path) -> list[dict]:
    try:
        return read_journal(path)[1]
    except UserError as error:
        raise SystemExit(f"insertion_stops: {error}") from None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("journal", type=Path, help="a policy's rvt2 eval journal (episodes.jsonl)")
    parser.add_argument("--searched", type=Path, help="an `rvt2 eval` folder of the same episodes with the search (a --replay of the journal, or the same checkpoint)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", help="write the stops here")
    args = parser.parse_args()
    if not args.journal.is_file():
        raise SystemExit(f"insertion_stops: {args.journal}: no such evaluation journal (an episodes.jsonl)")
    records = [r for r in _journal(args.journal) if r["task"] == "insert_peg" and r["source"] == "policy"]
    if not records:
        raise SystemExit(f"insertion_stops: {args.journal}: no insert_peg episodes of a policy")
    searched = {}
    if args.searched:
        if not (args.searched / NAME).is_file():
            raise SystemExit(f"insertion_stops: {args.searched / NAME}: no evaluation journal; give an `rvt2 eval --out` folder")
        searched = {r["seed"]: r["success"] for r in _journal(args.searched / NAME) if r["task"] == "insert_peg"}
    with ProcessPoolExecutor(args.workers) as pool:
        stops = list(pool.map(first_insertion_stop, records))
    for stop in stops:
        if stop["seed"] in searched:
            stop["searched_success"] = searched[stop["seed"]]
    inserted = [s for s in stops if s["insertion"] is not None]
    bands = [_band(0.0)] + [_band(b + 1e-9) for b in BANDS_MM]
    print(f"insert_peg, {len(records)} episodes, {len(inserted)} with an insertion; the peg's head after the first, "
          "pushed straight, across the hole's axis:\n")
    print("| across the axis | episodes | went in | success with the search | peg slid back in the fingers, median mm |\n"
          "|---|---|---|---|---|")
    rows = []
    for band in bands:
        mine = [s for s in inserted if _band(s["across_mm"]) == band]
        went = sum(s["went_in"] for s in mine)
        found = sum(s.get("searched_success", False) for s in mine)
        slid = float(np.median([s["slid_back_mm"] for s in mine if not s["went_in"]])) if any(not s["went_in"] for s in mine) else None
        rows.append({"band": band, "episodes": len(mine), "went_in": went, "searched_success": found if searched else None,
                     "slid_back_mm_median_not_in": slid})
        print(f"| {band} | {len(mine)} | {went} | {found if searched else '-'} | {'-' if slid is None else f'{slid:.0f}'} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": describe(), "journal": str(args.journal), "searched": str(args.searched or ""),
                       "rows": rows, "stops": stops}, f, indent=2)


if __name__ == "__main__":
    main()
