"""One evaluation episode: observe -> predict the next keyframe -> execute -> repeat, until the
task's own success check passes or a budget runs out.

Keyframes come from a `KeyframeSource`: the trained policy (`PolicySource`) or the ground truth
(`OracleSource`: a recorded demo's keyframes, or the scripted expert's on the same seed), so the
oracle measures the executor's ceiling with everything else the same.
"""

import random
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from rvt2cli.data.fusion import fuse
from rvt2cli.eval.executor import Executor, KeyframeAction, StepBudgetExhausted
from rvt2cli.record.scene import capture_cameras, held_objects, segmentation_ids
from rvt2cli.tasks import Task

FAILURE_KINDS = ("planning_failure", "budget_exhausted", "task_failed", "error")


@dataclass
class Step:
    """One keyframe prediction and what became of it."""

    frame: int              # control steps done before it
    action: KeyframeAction
    reached: bool           # False: no plan reached the pose


@dataclass
class Outcome:
    task: str
    seed: int
    success: bool
    failure: str | None     # one of FAILURE_KINDS, None on success
    steps: list[Step] = field(default_factory=list)
    control_steps: int = 0
    collision_fallbacks: int = 0   # keyframes reached only by planning without the scene cloud
    control_hz: float = 20.0
    instruction: str = ""
    error: str | None = None
    video: list[np.ndarray] = field(default_factory=list, repr=False)

    @property
    def keyframes(self) -> int:
        return len(self.steps)


class KeyframeSource:
    def reset(self, task: Task, seed: int, instruction: str) -> None:
        raise NotImplementedError

    def next(self, cloud, gripper_open: bool, finger_positions, keyframes_done: int) -> KeyframeAction | None:
        """The next keyframe, or None when the source has nothing more to do."""
        raise NotImplementedError


def _collision_points(env, frames, segmentation, bounds) -> np.ndarray:
    """The scene cloud for the planner: without the robot, and without what it holds (it moves with it)."""
    drop = segmentation_ids(env, held_objects(env), include_robot=True)
    scene = {name: replace(frame, depth=np.where(np.isin(segmentation[name], drop), 0.0, frame.depth).astype(np.float32))
             for name, frame in frames.items()}
    return fuse(scene, bounds).xyz


def run_episode(env, task: Task, seed: int, source: KeyframeSource, instruction: str, keyframe_budget: int = 25,
                step_budget: int | None = None, video_every: int = 0) -> Outcome:
    source.reset(task, seed, instruction)  # first: the oracle may run the expert on this seed
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    env.reset(seed=seed)
    executor = Executor(env, step_budget or task.max_steps, task.planner_speed, task.gripper_close)
    outcome = Outcome(task=task.name, seed=seed, success=False, failure=None, instruction=instruction,
                      control_hz=float(env.unwrapped.control_freq))
    if video_every:
        def grab():
            if executor.steps % video_every == 0:
                outcome.video.append(np.asarray(env.render()[0].cpu().numpy(), dtype=np.uint8))
        executor.on_step = grab
        grab()
    planning_failures = 0
    try:
        for k in range(keyframe_budget):
            segmentation: dict = {}
            frames = capture_cameras(env, segmentation)
            cloud = fuse(frames, task.scene_bounds)
            qpos = env.unwrapped.agent.robot.get_qpos()[0].cpu().numpy()
            action = source.next(cloud, executor.gripper > 0, qpos[-2:], k)
            if action is None:
                break
            scene_points = None if action.ignore_collisions else _collision_points(env, frames, segmentation, task.scene_bounds)
            frame = executor.steps
            reached = executor.execute(action, scene_points)
            planning_failures += not reached
            outcome.steps.append(Step(frame=frame, action=action, reached=reached))
            if bool(env.unwrapped.evaluate()["success"].item()):
                outcome.success = True
                break
    except StepBudgetExhausted:
        outcome.success = bool(env.unwrapped.evaluate()["success"].item())
    outcome.control_steps = executor.steps
    outcome.collision_fallbacks = executor.collision_fallbacks
    if not outcome.success:
        if planning_failures:
            outcome.failure = "planning_failure"
        elif len(outcome.steps) >= keyframe_budget or executor.steps >= executor.step_budget:
            outcome.failure = "budget_exhausted"
        else:
            outcome.failure = "task_failed"  # the source stopped (the oracle ran out of keyframes)
    return outcome
