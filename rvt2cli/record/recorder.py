"""`rvt2 record`: expert demonstrations -> one MCAP episode file per successful episode.

The expert runs without rendering; afterwards the scene is restored (`set_state_dict`) at the frames
training needs and only those are rendered: frame 0, every `obs_every`-th frame and every keyframe of
the default rule. Each file also carries its keyframes and training samples (`rvt2 extract-keyframes`' rule
with the recording's obs_every), found in the trajectory as it is written. Episodes use seeds seed, seed+1,
...; with several workers, episodes are accepted in seed order, so the same command always writes the same
files. A task with variations spreads its episodes over them: the seed picks the variation
(`rvt2cli.tasks.episode_variation`).
"""

import time
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rvt2cli.atomic import ensure_folder
from rvt2cli.data import EpisodeMeta, EpisodeWriter
from rvt2cli.data.fusion import fuse
from rvt2cli.data.keyframes import KeyframeAnnotation
from rvt2cli.data.provenance import software_versions
from rvt2cli.keyframes.extract import annotate_trajectory
from rvt2cli.keyframes.rule import KeyframeParams, find_keyframes
from rvt2cli.errors import UserError
from rvt2cli.record.expert import ExpertRun, load_expert, run_expert
from rvt2cli.record.robot_visuals import DESCRIPTION as ROBOT_VISUALS
from rvt2cli.record.capture import capture_cameras, capture_path
from rvt2cli.record.scene import make_env, restore_sim_state
from rvt2cli.robot import RobotFacts
from rvt2cli.runtime import use_vulkan_driver, worker_pool
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
    experts: tuple[tuple[str, str], ...] = ()  # (task, "module:function"): another expert than the task's
    keyframes: bool = True    # annotate each episode as `rvt2 extract-keyframes` would, with obs_every, as it is written

    def task(self, name: str) -> Task:
        """The task as recorded: its expert replaced where `experts` names another."""
        task = get_task(name)
        expert = dict(self.experts).get(name)
        return replace(task, expert=expert) if expert else task


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


def recorded_keyframes(run: ExpertRun, arm_velocities: np.ndarray, obs_frames: list[int], obs_every: int) -> KeyframeAnnotation:
    """The keyframes and samples `rvt2 extract-keyframes --obs-every N` finds in the written file, from the
    trajectory in memory: the same arrays as the file gives back (its dtypes), so the same annotation."""
    frames = run.frames
    near = [sorted(f.near) for f in frames] if all(f.near is not None for f in frames) else None
    return annotate_trajectory(len(frames), obs_frames, np.array([f.gripper_command for f in frames], dtype=np.float32),
                               arm_velocities, [sorted(f.contacts) for f in frames],
                               np.array([f.state["tcp_pose"] for f in frames], dtype=np.float64), near,
                               KeyframeParams(obs_every=obs_every)).keyframes


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
        arm_velocities = robot.arm(np.array([f.state["joint_velocities"] for f in run.frames], dtype=np.float32),  # as read back
                                   run.frames[0].state["joint_names"])
        for t in observation_frames(len(run.frames), gripper_open, arm_velocities, options.obs_every):
            restore_sim_state(env, run.frames[t].sim)
            images = capture_cameras(env)
            cloud = fuse(images, task.scene_bounds, options.voxel_size) if options.store_clouds else None
            writer.write_observation(t, images, cloud)
        if options.keyframes:
            writer.write_keyframes(recorded_keyframes(run, arm_velocities, writer.obs_frames, options.obs_every))
        meta = EpisodeMeta(
            task=task.name, env_id=task.env_id, seed=run.seed, success=run.success, expert=task.expert,
            num_frames=len(run.frames), control_hz=control_hz, scene_bounds=list(task.scene_bounds), cameras=cameras,
            instruction=instruction, obs_frames=writer.obs_frames,
            versions=software_versions("mani-skill", "sapien", "mplib", "numpy"),
            voxel_size=options.voxel_size, extra={"image_size": int(options.image_size or task.image_size), "status": run.status,
                                                  "robot": robot.to_json(), "variation": run.variation,
                                                  "renderer": use_vulkan_driver().name,  # the Vulkan driver that drew the cameras
                                                  "capture": capture_path(env),   # a camera group or camera by camera
                                                  "robot_visuals": ROBOT_VISUALS},
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


# --- parallel recording: one pool of simulator processes for every task ----------------------------

_worker_scene = {"task": None, "env": None}
_worker_args = None


def _init_worker(out_dir: str, options: RecordOptions) -> None:
    global _worker_args
    _worker_args = (Path(out_dir), options)


def _work(task_name: str, seed: int) -> EpisodeResult:
    """Record one episode in this worker, building the task's scene first if its last one was another task's."""
    out_dir, options = _worker_args
    task = _worker_scene["task"]
    if task is None or task.name != task_name:
        if _worker_scene["env"] is not None:
            _worker_scene["env"].close()
        task = options.task(task_name)
        _worker_scene.update(task=task, env=make_env(task, options.cameras, options.image_size))
    return record_episode(_worker_scene["env"], task, seed, out_dir, options)


@dataclass
class RecordSummary:
    task: str
    requested: int
    results: list[EpisodeResult] = field(default_factory=list)
    seconds: float = 0.0   # from the start of the recording until this task had its episodes (or gave up)

    @property
    def successes(self) -> list[EpisodeResult]:
        return [r for r in self.results if r.success]

    @property
    def expert_success_rate(self) -> float:
        return len(self.successes) / max(1, len(self.results))

    @property
    def complete(self) -> bool:
        return len(self.successes) >= self.requested

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


def check_experts(experts, task_names, doing: str = "being recorded") -> None:
    """Each replacement expert names a task of `task_names` and a function that imports: one line otherwise,
    before any simulator starts."""
    for name, spec in experts:
        if name not in task_names:
            raise UserError(f"--expert {name}={spec}: {name} is not among the tasks {doing} ({', '.join(task_names)})")
        try:
            load_expert(spec)
        except (ImportError, AttributeError, ValueError):
            raise UserError(f"--expert {name}={spec}: no such function; give module:function, e.g. "
                            "rvt2cli.record.rlbench18.reach_and_drag:expert_via_target") from None


def record(task_name: str, episodes: int, out_dir: str | Path, seed: int = 0, workers: int = 1,
           options: RecordOptions = RecordOptions(), max_attempts: int | None = None, on_result=None) -> RecordSummary:
    """Record `episodes` successful episodes of one task (seeds from `seed` upwards); see `record_tasks`."""
    return record_tasks([task_name], episodes, out_dir, seed, workers, options, max_attempts, on_result)[0]


def record_tasks(task_names, episodes: int, out_dir: str | Path, seed: int = 0, workers: int = 1,
                 options: RecordOptions = RecordOptions(), max_attempts: int | None = None,
                 on_result=None) -> list[RecordSummary]:
    """Record `episodes` successful episodes of each task, seeds from `seed` upwards, giving up on a task
    after `max_attempts` seeds. `on_result(result, summary)` is called for every attempt, in seed order
    within a task (the CLI's progress bar). With several workers one pool serves all tasks: a worker
    builds a task's scene when it is first given one of its seeds, so the processes start once and none
    waits at the end of one task while another has seeds left."""
    tasks = [options.task(name) for name in task_names]
    for task in tasks:
        task.variation_choices(options.variations)  # an unknown variation is the user's error, before any simulator starts
    check_experts(options.experts, task_names)
    out_dir = ensure_folder(out_dir)
    max_attempts = max_attempts or 10 * episodes + 10
    summaries = [RecordSummary(task=task.name, requested=episodes) for task in tasks]
    start = time.perf_counter()
    if workers <= 1:
        for task, summary in zip(tasks, summaries):
            env = make_env(task, options.cameras, options.image_size)
            try:
                for s in range(seed, seed + max_attempts):
                    _accept(summary, record_episode(env, task, s, out_dir, options), on_result)
                    if summary.complete:
                        break
            finally:
                env.close()
            summary.seconds = time.perf_counter() - start
    else:
        _record_parallel(tasks, summaries, out_dir, seed, workers, options, max_attempts, on_result, start)
    return summaries


def _accept(summary: RecordSummary, result: EpisodeResult, on_result) -> None:
    summary.results.append(result)
    if on_result:
        on_result(result, summary)


@dataclass
class _TaskSeeds:
    """One task's seeds in a shared pool: handed out in order, their results accepted in order."""
    summary: RecordSummary
    next_seed: int
    last_seed: int
    frontier: int
    finished: dict = field(default_factory=dict)   # seed -> result, done but not yet accepted
    running: int = 0

    def can_start(self) -> bool:
        return not self.summary.complete and self.next_seed < self.last_seed

    def needs(self) -> bool:
        """Whether more seeds are needed even if every one running succeeds."""
        waiting = sum(r.success for r in self.finished.values())
        return self.can_start() and len(self.summary.successes) + waiting + self.running < self.summary.requested


def _record_parallel(tasks, summaries, out_dir, seed, workers, options, max_attempts, on_result, start) -> None:
    queues = {task.name: _TaskSeeds(summary, seed, seed + max_attempts, seed) for task, summary in zip(tasks, summaries)}
    leftovers: list[EpisodeResult] = []

    def next_job():
        # Seeds a task needs come first, in task order; then, rather than idle, seeds a task may need
        # (a worker runs ahead; its episode is dropped below if the task completes without it).
        for wanted in (_TaskSeeds.needs, _TaskSeeds.can_start):
            for name, queue in queues.items():
                if wanted(queue):
                    queue.next_seed += 1
                    queue.running += 1
                    return name, queue.next_seed - 1
        return None

    # The renderer is chosen (and probed) once here and inherited by the workers. Rendering with lavapipe,
    # they need no GPU: hidden from them, they open no CUDA context (ManiSkill's resets would open one).
    driver = use_vulkan_driver()
    with worker_pool(workers, _init_worker, (str(out_dir), options), gpus="none" if driver.name == "lavapipe" else "one") as pool:
        pending = {}
        while True:
            while len(pending) < workers and (job := next_job()) is not None:
                pending[pool.submit(_work, *job)] = job
            if not pending:
                break
            completed, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in completed:
                name, done_seed = pending.pop(future)
                queue = queues[name]
                queue.running -= 1
                result = future.result()
                if queue.summary.complete:
                    leftovers.append(result)
                    continue
                queue.finished[done_seed] = result
                while queue.frontier in queue.finished and not queue.summary.complete:
                    _accept(queue.summary, queue.finished.pop(queue.frontier), on_result)
                    queue.frontier += 1
                if queue.summary.complete:
                    queue.summary.seconds = time.perf_counter() - start
                    leftovers += queue.finished.values()
                    queue.finished.clear()
    # Episodes past the last one a task needed were recorded only because workers ran ahead: drop them,
    # so that the files do not depend on the number of workers.
    for result in leftovers:
        if result.path:
            Path(result.path).unlink(missing_ok=True)
    for queue in queues.values():
        if not queue.summary.complete:
            queue.summary.seconds = time.perf_counter() - start
