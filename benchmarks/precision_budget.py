"""How precise must a policy be? The oracle (the scripted expert's keyframes, run by `rvt2 eval`'s
executor) with its keyframes degraded the way a policy's predictions are, on the same seeds:

- `exact`: the keyframes as the expert reached them;
- `rotN`: each keyframe's rotation snapped to the centre of its Euler-angle bin, N bins per axis, by the
  functions the policy decodes its rotation with (`rvt2cli.model.rotation`): 72 is the paper's 5 degrees;
- `posM`: each keyframe moved M mm in a random direction (seeded per episode);
- `turnD`: each keyframe turned D degrees about a random axis (seeded per episode): a policy's
  rotation error, where `rotN` is only its quantisation;
- `A+B`: both, e.g. `rot360+pos2`.

    python -m benchmarks.precision_budget [--tasks insert_peg,plug_charger] [--variants exact,rot72,rot360,pos2]
                                          [--seeds 20] [--first-seed 10000] [--workers 2] [--json out.json]
                                          [--no-insertion-search] [--search-pitch MM] [--search-retract MM]

Per task and variant: success (Wilson 95% interval) and, for insertion tasks, the median closest gap to
success of the failed episodes. Every episode is `rvt2cli.eval.rollout.run_episode`, the loop `rvt2 eval`
runs. `--search-pitch` / `--search-retract` run the insertion search with another grid than the tasks'
tasks/*.toml give (`search_pitch_mm`, `search_retract_mm`), to compare grids on seeds no policy is scored on.
"""

import argparse
import json
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks.machine import describe
from rvt2cli.data.keyframes import Keyframe
from rvt2cli.eval.report import wilson_interval
from rvt2cli.eval.sources import OracleSource
from rvt2cli.model.rotation import bins_to_quaternion, quaternion_to_bins


# a variant's prefix -> the Degradation field its number sets, and the number's type
VARIANT_PREFIXES = {"rot": ("rotation_bins", int), "pos": ("position_mm", float), "turn": ("turn_deg", float)}


@dataclass(frozen=True)
class Degradation:
    rotation_bins: int = 0       # > 0: snap rotations to bin centres
    position_mm: float = 0.0     # > 0: move each keyframe this far in a random direction
    turn_deg: float = 0.0        # > 0: turn each keyframe this far about a random axis

    @staticmethod
    def parse(name: str) -> "Degradation":
        fields = {}
        for part in filter(lambda p: p != "exact", name.split("+")):
            prefix = next((p for p in VARIANT_PREFIXES if part.startswith(p)), None)
            try:
                field, kind = VARIANT_PREFIXES[prefix]
                fields[field] = kind(part[len(prefix):])
            except (KeyError, ValueError):
                raise SystemExit(f"precision_budget: unknown variant {part!r} (exact, rotN, posM, turnD, A+B)") from None
        return Degradation(**fields)

    def apply(self, keyframe: Keyframe, rng: np.random.Generator) -> Keyframe:
        position, quaternion = np.asarray(keyframe.position, float), np.asarray(keyframe.quaternion, float)
        if self.rotation_bins:
            quaternion = bins_to_quaternion(quaternion_to_bins(quaternion, self.rotation_bins), self.rotation_bins)
        if self.position_mm:
            direction = rng.normal(size=3)
            position = position + self.position_mm / 1000.0 * direction / np.linalg.norm(direction)
        if self.turn_deg:
            axis = rng.normal(size=3)
            turn = Rotation.from_rotvec(np.radians(self.turn_deg) * axis / np.linalg.norm(axis))
            quaternion = (turn * Rotation.from_quat(quaternion)).as_quat()
        return Keyframe.from_pose([*position, *quaternion], keyframe.gripper_open, keyframe.ignore_collisions,
                                  keyframe.frame, keyframe.reasons)


class DegradedOracle(OracleSource):
    def __init__(self, env, degradation: Degradation):
        super().__init__(env)
        self.degradation = degradation

    def reset(self, task, seed, instruction):
        super().reset(task, seed, instruction)
        rng = np.random.default_rng(seed)
        self.queue = [self.degradation.apply(k, rng) for k in self.queue]


_envs: dict = {}


def _episode(job: tuple[str, str, int, bool, dict]) -> dict:
    from rvt2cli.eval.rollout import run_episode
    from rvt2cli.record.scene import make_env
    from rvt2cli.tasks import get_task

    variant, task_name, seed, search, grid = job
    task = replace(get_task(task_name), **grid)
    env = _envs.setdefault(task_name, make_env(task))
    outcome = run_episode(env, task, seed, DegradedOracle(env, Degradation.parse(variant)), task.instruction(seed)[0],
                          step_budget=2 * task.max_steps, search=search)
    gaps = [s.gap_mm for s in outcome.steps if s.gap_mm is not None and s.held]
    return {"variant": variant, "task": task_name, "seed": seed, "success": outcome.success,
            "failure": outcome.failure, "closest_gap_mm": min(gaps) if gaps else None,
            "probes": sum(s.reach.probes for s in outcome.steps)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="insert_peg,plug_charger")
    parser.add_argument("--variants", default="exact,rot72,rot360,pos2")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=10_000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--no-insertion-search", dest="search", action="store_false",
                        help="push insertions straight, without the executor's search for the hole")
    parser.add_argument("--search-pitch", type=float, metavar="MM",
                        help="the insertion search's grid pitch for every task in --tasks (default: tasks/*.toml's)")
    parser.add_argument("--search-retract", type=float, metavar="MM",
                        help="how far each probe backs off the face (default: tasks/*.toml's)")
    parser.add_argument("--json", help="write results here")
    args = parser.parse_args()
    grid = {k: v for k, v in (("search_pitch_mm", args.search_pitch), ("search_retract_mm", args.search_retract))
            if v is not None}
    if any(v <= 0 for v in grid.values()):
        raise SystemExit("precision_budget: --search-pitch and --search-retract must be > 0 (mm)")
    tasks, variants = args.tasks.split(","), args.variants.split(",")
    for v in variants:
        Degradation.parse(v)
    jobs = [(v, t, args.first_seed + i, args.search, grid) for t in tasks for v in variants for i in range(args.seeds)]
    with ProcessPoolExecutor(args.workers) as pool:
        episodes = list(pool.map(_episode, jobs))
    rows = []
    print("| task | variant | success (95% CI) | failed: median closest gap mm |\n|---|---|---|---|")
    for t in tasks:
        for v in variants:
            mine = [e for e in episodes if e["task"] == t and e["variant"] == v]
            wins = sum(e["success"] for e in mine)
            lo, hi = wilson_interval(wins, len(mine))
            gaps = [e["closest_gap_mm"] for e in mine if not e["success"] and e["closest_gap_mm"] is not None]
            gap = float(np.median(gaps)) if gaps else None
            rows.append({"task": t, "variant": v, "successes": wins, "episodes": len(mine), "ci95": [lo, hi],
                         "median_gap_mm": gap})
            print(f"| {t} | {v} | {wins / len(mine):.0%} ({wins}/{len(mine)}; {lo:.0%}-{hi:.0%}) | "
                  f"{'-' if gap is None else f'{gap:.1f}'} |", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": describe(), "first_seed": args.first_seed, "insertion_search": args.search,
                       "search_grid_mm": grid, "rows": rows,
                       "episodes": episodes}, f, indent=2)


if __name__ == "__main__":
    main()
