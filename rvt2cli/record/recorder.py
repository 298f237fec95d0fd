"""`rvt2 record`: expert demonstrations -> one MCAP episode file per successful episode.

The expert runs without rendering; afterwards the scene is restored (`set_state_dict`) at the frames
training needs and only those are rendered: frame 0, every `obs_every`-th frame and every keyframe of
the default rule. Episodes use seeds seed, seed+1, ...; with several workers, episodes are accepted in
seed order, so the same command always writes the same files. A task with variations spreads its
episodes over them: the seed picks the variation (`rvt2cli.tasks.episode_variation`).
"""

import multiprocessing
import os
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rvt2cli.atomic import ensure_folder
from rvt2cli.data import EpisodeMeta, EpisodeWriter
from rvt2cli.data.fusion import fuse
from rvt2cli.data.provenance import software_versions
from rvt2cli.keyframes.rule import KeyframeParams, find_keyframes
from rvt2cli.record.expert import ExpertRun, run_expert
from rvt2cli.record.scene import capture_cameras, make_env, restore_sim_state
from rvt2cli.robot import RobotFacts
from rvt2cli.runtime import end_with_parent
from rvt2cli.tasks import Task, episode_variation, get_task


@dataclass(frozen=True)
class RecordOptions:
    cameras: tuple[str, ...] | None = None   # None: the task's rig
    image_size: int | None = None
    obs_every: int = 10
    voxel_size: float | None = None
    store_clouds: bool = False
    keep_failures: bool = False
    variations: str = "all"   # which the episodes spread over: all, seen (not the held-out split) or one index


@dataclass
class EpisodeResult:
    seed: int
    status: str
    frames: int
    seconds: float
    variation: int = 0
    path: str | None = None
    size_bytes: int = 0
    error: str | None = None

    @property
    def success(self) -> bool:
        return self.status == "success"


def episode_path(out_dir: Path, task: Task, seed: int) -> Path:
    return out_dir / f"{task.name}_{seed:04d}.mcap"



def observation_frames(num_frames: int, gripper_open, arm_velocities, obs_every: int) -> list[int]:
    """The frames whose images an episode stores: frame 0, every `obs_every`-th frame, every keyframe of
    the default rule and the last frame (`rvt2 record` and `rvt2 import-rosbag` alike). `gripper_open`
    [T] and `arm_velocities` [T, J] are the dense trajectory's, as `find_keyframes` takes them."""
    keyframes = find_keyframes(np.asarray(gripper_open, dtype=bool), np.asarray(arm_velocities),
                               KeyframeParams(obs_every=obs_every))
    return sorted(set(range(0, num_frames, obs_every)) | {k.frame for k in keyframes} | {num_frames - 1})


def write_episode(env, task: Task, run: ExpertRun, path: Path, options: RecordOptions) -> Path:
    control_hz = float(env.unwrapped.control_freq)
    instruction, template_index = task.instruction(run.seed, run.variation)
    cameras = list(env.rvt2_cameras)
    robot = RobotFacts.from_agent(env.unwrapped.agent)
    with EpisodeWriter(path, control_hz) as writer:
        writer.write_instruction(instruction, task.name, template_index, task.variation_values(run.variation),
                                 variation_index=run.variation)
        for t, frame in enumerate(run.frames):
            writer.write_frame(t, joint_names=frame.state["joint_names"], joint_positions=frame.state["joint_positions"],
                               joint_velocities=frame.state["joint_velocities"], gripper_width=frame.state["gripper_width"],
                               gripper_command=frame.gripper_command, action=frame.action, contacts=frame.contacts,
                               tcp_pose=frame.state["tcp_pose"], sim_state=frame.sim, near=frame.near)
        gripper_open = [f.gripper_command > 0 for f in run.frames]
        arm_velocities = robot.arm(np.array([f.state["joint_velocities"] for f in run.frames]), run.frames[0].state["joint_names"])
        for t in observation_frames(len(run.frames), gripper_open, arm_velocities, options.obs_every):
            restore_sim_state(env, run.frames[t].sim)
            images = capture_cameras(env)
            cloud = fuse(images, task.scene_bounds, options.voxel_size) if options.store_clouds else None
            writer.write_observation(t, images, cloud)
        meta = EpisodeMeta(
            task=task.name, env_id=task.env_id, seed=run.seed, success=run.success, expert=task.expert,
            num_frames=len(run.frames), control_hz=control_hz, scene_bounds=list(task.scene_bounds), cameras=cameras,
            instruction=instruction, obs_frames=writer.obs_frames,
            versions=software_versions("mani-skill", "sapien", "mplib", "numpy"),
            voxel_size=options.voxel_size, extra={"image_size": int(options.image_size or task.image_size), "status": run.status,
                                                  "robot": robot.to_json(), "variation": run.variation},
        )
        return writer.finish(meta)


def record_episode(env, task: Task, seed: int, out_dir: Path, options: RecordOptions) -> EpisodeResult:
    start = time.perf_counter()
    variation = episode_variation(seed, task.variation_choices(options.variations))
    try:
        run = run_expert(env, task.expert, seed, max_frames=task.max_steps, variation=variation)
    except Exception as e:  # noqa: BLE001 - a simulator or expert crash costs one episode, not the run
        return EpisodeResult(seed, "error", 0, time.perf_counter() - start, variation, error=f"{type(e).__name__}: {e}")
    result = EpisodeResult(seed, run.status, len(run.frames), 0.0, variation)
    if run.success or options.keep_failures:
        path = write_episode(env, task, run, episode_path(out_dir, task, seed), options)
        result.path, result.size_bytes = str(path), path.stat().st_size
    result.seconds = time.perf_counter() - start
    return result


# --- parallel recording: one simulator per worker process ------------------------------------------

_worker_env = None
_worker_args = None


def _init_worker(task_name: str, out_dir: str, options: RecordOptions) -> None:
    global _worker_env, _worker_args
    end_with_parent()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    task = get_task(task_name)
    _worker_env = make_env(task, options.cameras, options.image_size)
    _worker_args = (task, Path(out_dir), options)


def _work(seed: int) -> EpisodeResult:
    task, out_dir, options = _worker_args
    return record_episode(_worker_env, task, seed, out_dir, options)


@dataclass
class RecordSummary:
    task: str
    requested: int
    results: list[EpisodeResult] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def successes(self) -> list[EpisodeResult]:
        return [r for r in self.results if r.success]

    @property
    def expert_success_rate(self) -> float:
        return len(self.successes) / max(1, len(self.results))

    def successes_per_variation(self) -> dict[int, int]:
        out: dict[int, int] = {}
        for r in self.successes:
            out[r.variation] = out.get(r.variation, 0) + 1
        return dict(sorted(out.items()))

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for r in self.results:
            out[r.status] = out.get(r.status, 0) + 1
        return out


def record(task_name: str, episodes: int, out_dir: str | Path, seed: int = 0, workers: int = 1,
           options: RecordOptions = RecordOptions(), max_attempts: int | None = None, on_result=None) -> RecordSummary:
    """Record `episodes` successful episodes (seeds from `seed` upwards). `on_result(result, summary)`
    is called for every attempt in seed order (the CLI's progress bar)."""
    task = get_task(task_name)
    task.variation_choices(options.variations)  # an unknown variation is the user's error, before any simulator starts
    out_dir = ensure_folder(out_dir)
    max_attempts = max_attempts or 10 * episodes + 10
    summary = RecordSummary(task=task.name, requested=episodes)
    start = time.perf_counter()

    def accept(result: EpisodeResult) -> None:
        summary.results.append(result)
        if on_result:
            on_result(result, summary)

    if workers <= 1:
        env = make_env(task, options.cameras, options.image_size)
        try:
            for s in range(seed, seed + max_attempts):
                accept(record_episode(env, task, s, out_dir, options))
                if len(summary.successes) >= episodes:
                    break
        finally:
            env.close()
    else:
        _record_parallel(task, episodes, out_dir, seed, workers, options, max_attempts, summary, accept)
    summary.seconds = time.perf_counter() - start
    return summary


def _record_parallel(task, episodes, out_dir, seed, workers, options, max_attempts, summary, accept) -> None:
    context = multiprocessing.get_context("spawn")  # SAPIEN does not survive fork
    finished: dict[int, EpisodeResult] = {}
    next_seed, frontier, last_seed = seed, seed, seed + max_attempts
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_init_worker,
                             initargs=(task.name, str(out_dir), options)) as pool:
        pending = {}
        done = False
        while not done:
            while len(pending) < workers and next_seed < last_seed:
                pending[pool.submit(_work, next_seed)] = next_seed
                next_seed += 1
            if not pending:
                break
            completed, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in completed:
                finished[pending.pop(future)] = future.result()
            while frontier in finished and not done:
                accept(finished.pop(frontier))
                frontier += 1
                done = len(summary.successes) >= episodes
        for future in pending:
            future.cancel()
        # Episodes past the last one needed were recorded only because workers ran ahead: drop them,
        # so that the files do not depend on the number of workers.
        for future in pending:
            if not future.cancelled():
                finished[pending[future]] = future.result()
    for result in finished.values():
        if result.path:
            Path(result.path).unlink(missing_ok=True)
