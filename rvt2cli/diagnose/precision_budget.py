"""How precise must a policy be? The oracle (the scripted expert's keyframes, run by `rvt2 eval`'s
executor) with its keyframes degraded the way a policy's predictions are, on the same seeds:

- `exact`: the keyframes as the expert reached them;
- `rotN`: each keyframe's rotation snapped to the centre of its Euler-angle bin, N bins per axis, by the
  functions the policy decodes its rotation with (`rvt2cli.model.rotation`): 72 is the paper's 5 degrees;
- `posM`: each keyframe moved M mm in a random direction (seeded per episode);
- `turnD`: each keyframe turned D degrees about a random axis (seeded per episode): a policy's
  rotation error, where `rotN` is only its quantisation;
- `aheadM`: each keyframe of a held object (the gripper closed there and at the keyframe before) moved M mm
  across the table towards the next place it goes: a policy that brings a stick or a broom down onto the cube
  or the dirt it should come down behind (rvt2-18's reach_and_drag and sweep failures);
- `A+B`: both, e.g. `rot360+pos2`.

    rvt2 diagnose precision-budget [--tasks insert_peg,plug_charger] [--variants exact,rot72,rot360,pos2]
                                   [--seeds 20] [--first-seed 10000] [--workers 2] [--json out.json]
                                   [--no-insertion-search] [--search-pitch MM] [--search-retract MM]
                                   [--expert TASK=MODULE:FUNCTION]

Per task and variant: success (Wilson 95% interval) and, for insertion tasks, the median closest gap to
success of the failed episodes. Every episode is `rvt2cli.eval.rollout.run_episode`, the loop `rvt2 eval`
runs. `--search-pitch` / `--search-retract` run the insertion search with another grid than the tasks'
tasks/*.toml give (`search_pitch_mm`, `search_retract_mm`), to compare grids on seeds no policy is scored on.
`--expert` measures another scripted expert's keyframes (as `rvt2 record --expert`): how much error its demos
would leave a policy room for, before a GPU trains on them.
"""

from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from rvt2cli.data.keyframes import Keyframe
from rvt2cli.errors import UserError
from rvt2cli.eval.report import wilson_interval
from rvt2cli.eval.sources import OracleSource
from rvt2cli.model.rotation import bins_to_quaternion, quaternion_to_bins


# a variant's prefix -> the Degradation field its number sets, and the number's type
VARIANT_PREFIXES = {"rot": ("rotation_bins", int), "pos": ("position_mm", float), "turn": ("turn_deg", float),
                    "ahead": ("ahead_mm", float)}


@dataclass(frozen=True)
class Degradation:
    rotation_bins: int = 0       # > 0: snap rotations to bin centres
    position_mm: float = 0.0     # > 0: move each keyframe this far in a random direction
    turn_deg: float = 0.0        # > 0: turn each keyframe this far about a random axis
    ahead_mm: float = 0.0        # > 0: move each held object's keyframe this far towards where it goes next

    @staticmethod
    def parse(name: str) -> "Degradation":
        fields = {}
        for part in filter(lambda p: p != "exact", name.split("+")):
            prefix = next((p for p in VARIANT_PREFIXES if part.startswith(p)), None)
            try:
                field, kind = VARIANT_PREFIXES[prefix]
                fields[field] = kind(part[len(prefix):])
            except (KeyError, ValueError):
                raise UserError(f"unknown variant {part!r}; give exact, rotN, posM, turnD, aheadM or A+B "
                                "(e.g. rot360+pos2)") from None
        return Degradation(**fields)

    def apply(self, keyframe: Keyframe, rng: np.random.Generator, ahead: np.ndarray | None = None) -> Keyframe:
        """`keyframe` degraded; `ahead`: the unit direction across the table `aheadM` moves it (`ahead_directions`)."""
        position, quaternion = np.asarray(keyframe.position, float), np.asarray(keyframe.quaternion, float)
        if self.ahead_mm and ahead is not None:
            position = position + self.ahead_mm / 1000.0 * ahead
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


def ahead_directions(positions, gripper_open, apart_m: float = 0.01) -> list[np.ndarray | None]:
    """For each keyframe of a held object (the gripper closed there and at the keyframe before), the unit direction
    across the table to the next keyframe more than `apart_m` away across it; None for the others."""
    positions = np.asarray(positions, float).reshape(-1, 3)
    out = []
    for i, here in enumerate(positions):
        direction = None
        if i > 0 and not gripper_open[i] and not gripper_open[i - 1]:
            for later in positions[i + 1:]:
                across = (later - here)[:2]
                if np.linalg.norm(across) > apart_m:
                    direction = np.array([*across / np.linalg.norm(across), 0.0])
                    break
        out.append(direction)
    return out


class DegradedOracle(OracleSource):
    def __init__(self, env, degradation: Degradation):
        super().__init__(env)
        self.degradation = degradation

    def reset(self, task, seed, instruction):
        super().reset(task, seed, instruction)
        rng = np.random.default_rng(seed)
        directions = ahead_directions([k.position for k in self.queue], [k.gripper_open for k in self.queue])
        self.queue = [self.degradation.apply(k, rng, ahead) for k, ahead in zip(self.queue, directions)]


_envs: dict = {}


def _episode(job: tuple[str, str, int, bool, dict, dict]) -> dict:
    from rvt2cli.eval.rollout import run_episode
    from rvt2cli.record.scene import make_env
    from rvt2cli.tasks import get_task

    variant, task_name, seed, search, grid, experts = job
    task = replace(get_task(task_name), **grid, **({"expert": experts[task_name]} if task_name in experts else {}))
    env = _envs.setdefault(task_name, make_env(task))
    outcome = run_episode(env, task, seed, DegradedOracle(env, Degradation.parse(variant)), task.instruction(seed)[0],
                          step_budget=2 * task.max_steps, search=search)
    gaps = [s.gap_mm for s in outcome.steps if s.gap_mm is not None and s.held]
    return {"variant": variant, "task": task_name, "seed": seed, "success": outcome.success,
            "failure": outcome.failure, "closest_gap_mm": min(gaps) if gaps else None,
            "probes": sum(s.reach.probes for s in outcome.steps)}


def budget(tasks, variants, seeds: int = 20, first_seed: int = 10_000, workers: int = 2, search: bool = True,
           grid: dict | None = None, experts: dict[str, str] | None = None) -> dict:
    """Every variant (`Degradation.parse`) of the oracle on `seeds` seeds of each task: one row per task and variant
    (success, its interval, the failed episodes' median closest gap) and every episode. `grid`: search_pitch_mm
    and/or search_retract_mm for every task, instead of tasks/*.toml's. `experts`: task -> "module:function", the
    expert whose keyframes are degraded, instead of the task's own."""
    from rvt2cli.record.recorder import check_experts
    from rvt2cli.tasks import get_task

    grid, experts = grid or {}, dict(experts or {})
    check_experts(experts.items(), list(tasks), doing="measured")
    if any(v <= 0 for v in grid.values()):
        raise UserError("--search-pitch and --search-retract must be > 0 (mm)")
    for name in tasks:
        get_task(name)   # an unknown task is one line before any episode runs
    for v in variants:
        Degradation.parse(v)
    jobs = [(v, t, first_seed + i, search, grid, experts) for t in tasks for v in variants for i in range(seeds)]
    if workers == 1:   # here, in this process: its scenes are closed after, not kept as a worker's are
        try:
            episodes = list(map(_episode, jobs))
        finally:
            for env in _envs.values():
                env.close()
            _envs.clear()
    else:
        with ProcessPoolExecutor(workers) as pool:
            episodes = list(pool.map(_episode, jobs))
    rows = []
    for t in tasks:
        for v in variants:
            mine = [e for e in episodes if e["task"] == t and e["variant"] == v]
            wins = sum(e["success"] for e in mine)
            gaps = [e["closest_gap_mm"] for e in mine if not e["success"] and e["closest_gap_mm"] is not None]
            rows.append({"task": t, "variant": v, "successes": wins, "episodes": len(mine),
                         "ci95": list(wilson_interval(wins, len(mine))), "median_gap_mm": float(np.median(gaps)) if gaps else None})
    return {"first_seed": first_seed, "insertion_search": search, "search_grid_mm": grid, "experts": experts,
            "rows": rows, "episodes": episodes}


def markdown(report: dict) -> str:
    lines = ["| task | variant | success (95% CI) | failed: median closest gap mm |", "|---|---|---|---|"]
    for r in report["rows"]:
        (lo, hi), gap = r["ci95"], r["median_gap_mm"]
        lines.append(f"| {r['task']} | {r['variant']} | {r['successes'] / r['episodes']:.0%} ({r['successes']}/{r['episodes']}; "
                     f"{lo:.0%}-{hi:.0%}) | {'-' if gap is None else f'{gap:.1f}'} |")
    return "\n".join(lines) + "\n"
