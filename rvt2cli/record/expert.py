"""Run a task's scripted expert and keep the dense robot and simulator state of every frame."""

import contextlib
import importlib
import io
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np

from rvt2cli.record.scene import robot_contacts, robot_state, set_variation, sim_state
from rvt2cli.runtime import seed_everything


class EpisodeTooLong(Exception):
    pass


@dataclass
class Frame:
    """Everything recorded at one frame. Frame t is the state after t actions."""

    state: dict               # robot_state(): joints, gripper width, TCP pose
    sim: dict                 # sim_state(): restores the scene exactly
    contacts: list[str]
    gripper_command: float    # command in effect: the last action's gripper value (+1 open at the start)
    action: list[float] | None = None  # the action applied at this frame; None at the last frame
    near: list[str] = field(default_factory=list)  # scene bodies within 5 mm (robot_contacts)


@dataclass
class ExpertRun:
    seed: int
    variation: int = 0
    frames: list[Frame] = field(default_factory=list)
    success: bool = False
    status: str = "failed"    # success | failed | planning_failed | too_long


class RecordingWrapper(gym.Wrapper):
    """Records a Frame after reset and after every step, whoever calls step (the expert's planner)."""

    def __init__(self, env, max_frames: int):
        super().__init__(env)
        self.frames: list[Frame] = []
        self.max_frames = max_frames

    def _record(self, gripper_command: float) -> None:
        touched, near = robot_contacts(self.env)
        self.frames.append(Frame(state=robot_state(self.env), sim=sim_state(self.env), contacts=touched,
                                 gripper_command=gripper_command, near=near))

    def reset(self, **kwargs):
        out = self.env.reset(**kwargs)
        self.frames = []
        self._record(gripper_command=1.0)
        return out

    def step(self, action):
        if len(self.frames) >= self.max_frames:
            raise EpisodeTooLong(f"expert exceeded {self.max_frames} frames")
        action = np.asarray(action, dtype=np.float64).reshape(-1)
        self.frames[-1].action = action.tolist()
        out = self.env.step(action)
        self._record(gripper_command=float(action[-1]))
        return out


def load_expert(spec: str):
    module, _, function = spec.partition(":")
    return getattr(importlib.import_module(module), function)


def run_expert(env, expert_spec: str, seed: int, max_frames: int, variation: int = 0) -> ExpertRun:
    """Reset the scene with `seed` in this variation and let the expert solve it, recording every frame."""
    seed_everything(seed)
    set_variation(env, variation)  # the expert resets the scene itself
    recorder = RecordingWrapper(env, max_frames)
    run = ExpertRun(seed=seed, variation=variation)
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # the experts print planner failures
            result = load_expert(expert_spec)(recorder, seed=seed)
        run.status = "planning_failed" if isinstance(result, int) and result == -1 else "failed"
    except EpisodeTooLong:
        run.status = "too_long"
    run.frames = recorder.frames
    if run.status == "failed":
        run.success = bool(env.unwrapped.evaluate()["success"].item())
        run.status = "success" if run.success else "failed"
    return run
