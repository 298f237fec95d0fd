"""Which of the expert's keyframes does a failing policy miss? Each keyframe of the oracle's episode (the scripted
expert's keyframes through the executor, `rvt2 eval --oracle`) against the policy's nearest keyframe on the same
task and seed, which lays out the same scene, in the policy's successes and its failures apart.

    rvt2 diagnose oracle-gap POLICY_JOURNAL... --oracle ORACLE_JOURNAL... [--tasks a,b] [--near-mm 20]

"Nearest" is the closest any keyframe of the policy's episode with the same gripper state came (all of them
where none has it): the closest the policy ever came to that keyframe, wherever in its episode. So a keyframe
whose distance is small in successes and large in failures is one the failures never reach: for reach_and_drag
the stick's approach behind the cube, not the colour. Keyframes are counted by their place in the oracle's
episode (0, 1, ...); an episode with fewer keyframes leaves the later rows.

Where the oracle's keyframe carries a held tool, "ahead" is how far the policy's nearest keyframe lies beyond it
towards where the tool goes next (mm, negative: short of it; precision-budget's `aheadM` moves the oracle's so):
rvt2-18's failed drags and sweeps bring the tool down ahead, onto what it should come down behind.
"""

from collections import defaultdict

import numpy as np

from rvt2cli.diagnose.precision_budget import ahead_directions
from rvt2cli.errors import UserError
from rvt2cli.eval.journal import read_records


def nearest(policy_steps: list[dict], oracle_steps: list[dict]) -> list[tuple[float, float | None]]:
    """For each oracle keyframe, the distance (mm) to the nearest policy keyframe of the same gripper state, and how
    far (mm) that one lies ahead of it towards where a held tool goes next (None where it holds none)."""
    positions = np.array([s["target"][:3] for s in policy_steps], dtype=np.float64).reshape(-1, 3)
    gripper = np.array([bool(s["gripper_open"]) for s in policy_steps])
    oracle = np.array([s["target"][:3] for s in oracle_steps], dtype=np.float64).reshape(-1, 3)
    directions = ahead_directions(oracle, [bool(s["gripper_open"]) for s in oracle_steps])
    out = []
    for step, here, ahead in zip(oracle_steps, oracle, directions):
        same = gripper == bool(step["gripper_open"])
        candidates = positions[same] if same.any() else positions
        if not len(candidates):
            out.append((float("inf"), None))
            continue
        offsets = candidates - here
        closest = offsets[np.linalg.norm(offsets, axis=1).argmin()]
        out.append((float(np.linalg.norm(closest) * 1000.0), None if ahead is None else float(closest @ ahead * 1000.0)))
    return out


def report(policy_journals, oracle_journals, tasks=None, near_mm: float = 20.0) -> dict:
    """Per task and oracle keyframe: the policy's nearest distance in its successes and failures."""
    policy = [r for r in read_records(policy_journals) if r["source"] == "policy" and (not tasks or r["task"] in tasks)]
    oracle = {(r["task"], r["seed"]): r for r in read_records(oracle_journals) if r["source"] == "oracle"}
    paired = [(r, oracle[(r["task"], r["seed"])]) for r in policy if (r["task"], r["seed"]) in oracle]
    if not paired:
        raise UserError(f"no policy episode of {', '.join(map(str, policy_journals))} has an oracle episode on its task "
                        f"and seed in {', '.join(map(str, oracle_journals))}; give an `rvt2 eval --oracle` journal of "
                        "the same seeds")
    distances = defaultdict(lambda: {True: [], False: []})  # (task, keyframe) -> success -> [(mm, ahead mm)]
    for episode, reference in paired:
        for index, pair in enumerate(nearest(episode["steps"], reference["steps"])):
            distances[(episode["task"], index)][bool(episode["success"])].append(pair)
    rows = []
    for (task, index), by_outcome in sorted(distances.items()):
        row = {"task": task, "keyframe": index}
        for outcome, name in ((True, "successes"), (False, "failures")):
            mm = [d for d, _ in by_outcome[outcome]]
            ahead = [a for _, a in by_outcome[outcome] if a is not None]
            row[name] = {"episodes": len(mm), "median_mm": float(np.median(mm)) if mm else None,
                         "within_near": sum(d <= near_mm for d in mm),
                         "ahead_median_mm": float(np.median(ahead)) if ahead else None}
        rows.append(row)
    return {"policy_journals": [str(j) for j in policy_journals], "oracle_journals": [str(j) for j in oracle_journals],
            "near_mm": near_mm, "episodes": len(paired), "rows": rows}


def markdown(report: dict) -> str:
    near = f"{report['near_mm']:g}"
    lines = [f"the oracle's keyframes against the policy's nearest ({report['episodes']} episodes paired by task and seed)", "",
             f"| task | oracle keyframe | successes | nearest, median mm | ahead | failures | nearest, median mm | ahead "
             f"| failures within {near} mm |",
             "|---|---|---|---|---|---|---|---|---|"]

    def median(part, key="median_mm"):
        return "-" if part.get(key) is None else str(round(part[key]))
    for row in report["rows"]:
        won, lost = row["successes"], row["failures"]
        lines.append(f"| {row['task']} | {row['keyframe']} | {won['episodes']} | {median(won)} | {median(won, 'ahead_median_mm')} | "
                     f"{lost['episodes']} | {median(lost)} | {median(lost, 'ahead_median_mm')} | {lost['within_near']} |")
    return "\n".join(lines) + "\n"
