"""One evaluation episode: observe -> predict the next keyframe -> execute -> repeat, until the
task's own success check passes or a budget runs out.

Keyframes come from a `KeyframeSource`: the trained policy (`PolicySource`) or the ground truth
(`OracleSource`: a recorded demo's keyframes, or the scripted expert's on the same seed), so the
oracle measures the executor's ceiling with everything else the same.

When a predicted keyframe cannot be reached (no plan gets there), nothing in the scene changes, and a
deterministic policy would predict the same pose again until the budget is spent. Instead the source
is asked again (`retry` 1, 2, ...): the policy re-predicts from a seeded, perturbed observation; the
oracle has no alternative and moves on to its next keyframe. After `max_replans` unreachable
re-predictions in a row the episode ends as a planning failure.
"""

from dataclasses import dataclass, field, replace

import numpy as np

from rvt2cli.data.fusion import fuse
from rvt2cli.data.keyframes import Keyframe
from rvt2cli.eval.executor import Executor, Reach, StepBudgetExhausted
from rvt2cli.eval.options import MAX_REPLANS
from rvt2cli.eval.search import InsertionSearch
from rvt2cli.record.capture import capture_cameras, video_frame
from rvt2cli.record.scene import held_objects, segmentation_ids, set_variation
from rvt2cli.runtime import seed_everything
from rvt2cli.tasks import Task

FAILURE_KINDS = ("planning_failure", "budget_exhausted", "task_failed", "error")


@dataclass
class Step:
    """One keyframe prediction and what became of it."""

    frame: int              # control steps done before it
    keyframe: Keyframe
    reach: Reach
    retry: int = 0          # 0: the source's first prediction for this state; n: its n-th re-prediction
    held: bool = False      # an object is between the fingers after it
    gap_mm: float | None = None  # insertion tasks: how far the object is from success after it

    @property
    def reached(self) -> bool:
        return self.reach.reached


@dataclass
class Outcome:
    task: str
    seed: int
    success: bool
    failure: str | None     # one of FAILURE_KINDS, None on success
    steps: list[Step] = field(default_factory=list)
    control_steps: int = 0
    step_budget: int = 0    # the episode's control-step budget
    task_steps: int = 0     # the task's own max_steps (the budget at --step-budget-scale 1)
    control_hz: float = 20.0
    instruction: str = ""
    variation: int = 0
    wrong: str | None = None  # "wrong_object" / "wrong_target": what the task's check says went to another variation's
    final_check: dict = field(default_factory=dict)  # the task's check at the end: its numbers (e.g. stacked blocks)
    error: str | None = None
    video: list[np.ndarray] = field(default_factory=list, repr=False)

    @property
    def keyframes(self) -> int:
        return len(self.steps)

    @property
    def replans(self) -> int:
        return sum(s.retry > 0 for s in self.steps)

    @property
    def collision_fallbacks(self) -> int:
        return sum(s.reach.collision_fallback for s in self.steps)


class KeyframeSource:
    def reset(self, task: Task, seed: int, instruction: str) -> None:
        raise NotImplementedError

    def next(self, cloud, gripper_open: bool, finger_positions, keyframes_done: int, retry: int = 0) -> Keyframe | None:
        """The next keyframe, or None when the source has nothing (more) to offer. `retry` > 0 asks for
        an alternative to the last keyframe, which could not be reached."""
        raise NotImplementedError


def insertion_gap_mm(env, info: dict) -> float | None:
    """How far an insertion task's object is from success (0 when inside the task's tolerance), from
    what the ManiSkill task's own success check measures (`info`: its `evaluate()`); None for a task that
    measures no such thing."""
    if "peg_head_pos_at_hole" in info:   # PegInsertionSide: the peg's head in the hole's frame, x into the hole
        depth, across = info["peg_head_pos_at_hole"][0, 0].item(), info["peg_head_pos_at_hole"][0, 1:].abs().max().item()
        radius = env.unwrapped.box_hole_radii[0].item()
        return 1000.0 * float(np.hypot(max(0.0, -0.015 - depth), max(0.0, across - radius)))
    if "obj_to_goal_dist" in info:       # PlugCharger: success within 5 mm of the goal
        return 1000.0 * max(0.0, info["obj_to_goal_dist"][0].item() - 0.005)
    return None


def check_numbers(info: dict) -> dict:
    """A task's check (`evaluate()`: one-element tensors) as JSON numbers: flags as booleans, counts as ints."""
    out = {}
    for key, value in info.items():
        if hasattr(value, "numel") and value.numel() == 1:
            item = value.item()
            out[key] = item if isinstance(item, (bool, int)) else float(item)
    return out


def wrong_choice(info: dict) -> str | None:
    """"wrong_object" or "wrong_target" where the task's check (`info`: its `evaluate()`) says the gripper
    took, or the goal was reached by, what another variation asks for; None where it does not say so."""
    for kind in ("wrong_object", "wrong_target"):
        if kind in info and bool(info[kind].item()):
            return kind
    return None


def _collision_points(env, frames, segmentation, bounds) -> np.ndarray:
    """The scene cloud for the planner: without the robot, and without what it holds (it moves with it)."""
    drop = segmentation_ids(env, held_objects(env), include_robot=True)
    scene = {name: replace(frame, depth=np.where(np.isin(segmentation[name], drop), 0.0, frame.depth).astype(np.float32))
             for name, frame in frames.items()}
    return fuse(scene, bounds).xyz


def run_episode(env, task: Task, seed: int, source: KeyframeSource, instruction: str, keyframe_budget: int = 25,
                step_budget: int | None = None, video_every: int = 0, max_replans: int = MAX_REPLANS,
                search: bool = True, variation: int = 0) -> Outcome:
    """`search`: search for the hole where an insertion stops at a face (on tasks that give a pitch)."""
    seed_everything(seed)
    set_variation(env, variation)
    source.reset(task, seed, instruction)  # first: the oracle may run the expert on this seed (and variation)
    seed_everything(seed)
    set_variation(env, variation)  # whatever the source did to the scene
    env.reset(seed=seed)
    executor = Executor(env, step_budget or task.max_steps, task.planner_speed, task.gripper_close,
                        search=InsertionSearch.for_task(task) if search else None)
    outcome = Outcome(task=task.name, seed=seed, success=False, failure=None, instruction=instruction, variation=variation,
                      step_budget=executor.step_budget, task_steps=task.max_steps,
                      control_hz=float(env.unwrapped.control_freq))
    if video_every:
        def grab():
            if executor.steps % video_every == 0:
                outcome.video.append(video_frame(env))
        executor.on_step = grab
        grab()
    retry, stuck = 0, False
    try:
        while len(outcome.steps) < keyframe_budget:
            segmentation: dict = {}
            frames = capture_cameras(env, segmentation)
            cloud = fuse(frames, task.scene_bounds)
            keyframe = source.next(cloud, executor.gripper > 0, executor.finger_positions(), len(outcome.steps), retry)
            if keyframe is None:
                break
            scene_points = None if keyframe.ignore_collisions else _collision_points(env, frames, segmentation, task.scene_bounds)
            frame, spent = executor.steps, None
            try:
                reach = executor.execute(keyframe, scene_points)
            except StepBudgetExhausted as error:  # the keyframe the budget ran out in is kept, marked interrupted
                reach, spent = error.reach, error
            info = env.unwrapped.evaluate()
            outcome.steps.append(Step(frame=frame, keyframe=keyframe, reach=reach, retry=retry, held=bool(held_objects(env)),
                                      gap_mm=insertion_gap_mm(env, info) if task.insertion else None))
            if spent:
                raise spent
            if bool(info["success"].item()):
                outcome.success = True
                break
            retry = 0 if reach.reached else retry + 1
            if retry > max_replans:
                stuck = True
                break
    except StepBudgetExhausted:
        outcome.success = bool(env.unwrapped.evaluate()["success"].item())
    outcome.control_steps = executor.steps
    final = env.unwrapped.evaluate()
    outcome.final_check = check_numbers(final)
    if not outcome.success:
        outcome.wrong = wrong_choice(final)
        if stuck or any(not s.reached for s in outcome.steps):
            outcome.failure = "planning_failure"
        elif len(outcome.steps) >= keyframe_budget or executor.steps >= executor.step_budget:
            outcome.failure = "budget_exhausted"
        else:
            outcome.failure = "task_failed"  # the source stopped (the oracle ran out of keyframes)
    return outcome
