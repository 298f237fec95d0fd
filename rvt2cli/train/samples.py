"""Keyframe training samples, read from annotated episode files into memory.

A sample is the fused cloud at an observation frame, the proprio state there, the instruction, and
the next keyframe after it (position, orientation, gripper, collision flag) as the target.
"""

from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from rvt2cli import runtime
from rvt2cli.errors import UserError
from rvt2cli.model.observation import proprio_vector
from rvt2cli.train.cloud_spool import SpooledClouds, spool_clouds, spool_folder, unspool_clouds


# SampleSet's columns with one entry per sample; those in TABLE_OF index one of its tables.
TABLE_OF = {"task_index": "tasks", "instruction_index": "instructions", "episode_index": "episodes"}
PER_SAMPLE = ("xyz", "rgb", "proprio", "target_position", "target_quaternion", "target_gripper_open",
              "target_ignore_collisions", "keyframe_start", "keyframe_index", "final_keyframe", *TABLE_OF)


@dataclass
class SampleSet:
    tasks: list[str] = field(default_factory=list)
    instructions: list[str] = field(default_factory=list)
    bounds: dict[str, list[float]] = field(default_factory=dict)   # per task
    rigs: dict[str, dict] = field(default_factory=dict)            # per task: cameras and image size recorded with
    episodes: list[str] = field(default_factory=list)
    xyz: list[np.ndarray] = field(default_factory=list)            # per sample [N, 3] float32, world frame
    rgb: list[np.ndarray] = field(default_factory=list)            # per sample [N, 3] uint8
    proprio: list[np.ndarray] = field(default_factory=list)
    target_position: list[np.ndarray] = field(default_factory=list)
    target_quaternion: list[np.ndarray] = field(default_factory=list)  # xyzw
    target_gripper_open: list[bool] = field(default_factory=list)
    target_ignore_collisions: list[bool] = field(default_factory=list)
    task_index: list[int] = field(default_factory=list)
    instruction_index: list[int] = field(default_factory=list)
    episode_index: list[int] = field(default_factory=list)
    keyframe_start: list[bool] = field(default_factory=list)       # observed at frame 0 or at a keyframe
    keyframe_index: list[int] = field(default_factory=list)        # which keyframe of its episode the target is (-1: unknown)
    final_keyframe: list[bool] = field(default_factory=list)       # the target is its episode's last keyframe
    skipped_empty: int = 0
    skipped_failures: int = 0

    def __len__(self) -> int:
        return len(self.xyz)

    def subset(self, indices: list[int]) -> "SampleSet":
        """These samples only (the task, instruction and episode tables are kept whole)."""
        out = SampleSet(tasks=self.tasks, instructions=self.instructions, bounds=self.bounds, rigs=self.rigs,
                        episodes=self.episodes, skipped_empty=self.skipped_empty, skipped_failures=self.skipped_failures)
        for name in PER_SAMPLE:
            column = getattr(self, name)
            setattr(out, name, [column[i] for i in indices])
        return out

    def _index(self, table: list[str], value: str) -> int:
        if value not in table:
            table.append(value)
        return table.index(value)

    def extend(self, other: "SampleSet") -> int:
        """Append another set's samples (one episode's, from `episode_samples`), its tables merged into ours."""
        for name in PER_SAMPLE:
            if name not in TABLE_OF:
                getattr(self, name).extend(getattr(other, name))
        for column, table in TABLE_OF.items():
            ours = [self._index(getattr(self, table), value) for value in getattr(other, table)]
            getattr(self, column).extend(ours[i] for i in getattr(other, column))
        self.bounds.update(other.bounds)
        self.rigs.update(other.rigs)
        self.skipped_empty += other.skipped_empty
        return len(other)


def episode_samples(path: Path, keyframe_starts_only: bool = False, cameras: tuple[str, ...] | None = None) -> SampleSet:
    """An annotated episode's samples (with `keyframe_starts_only`, those observed at frame 0 or at a
    keyframe; with `cameras`, clouds fused from those cameras only)."""
    from rvt2cli.data.reader import read_episode

    ep = read_episode(path)
    if cameras and not set(cameras) <= set(ep.meta.cameras):
        missing = ", ".join(c for c in cameras if c not in ep.meta.cameras)
        raise UserError(f"{path}: has no camera {missing} (it has {', '.join(ep.meta.cameras)}); choose --cameras among them")
    samples = SampleSet(tasks=[ep.meta.task], instructions=[ep.instruction["text"]], episodes=[str(path)],
                        bounds={ep.meta.task: list(ep.meta.scene_bounds)},
                        rigs={ep.meta.task: {"cameras": list(cameras or ep.meta.cameras), "image_size": ep.meta.extra.get("image_size"),
                                             "renderer": ep.meta.extra.get("renderer"),
                                             "robot_visuals": ep.meta.extra.get("robot_visuals")}})
    annotation = ep.require_keyframes()
    starts = annotation.starts
    fingers = ep.meta.robot.fingers(ep.robot.joint_positions, ep.robot.joint_names, str(path))
    for sample in annotation.samples:
        frame, k = sample.obs_frame, sample.keyframe
        if keyframe_starts_only and frame not in starts:
            continue
        cloud = ep.cloud(frame, cameras)
        if len(cloud) == 0:
            samples.skipped_empty += 1
            continue
        target = annotation.keyframes[k]
        samples.xyz.append(cloud.xyz)
        samples.rgb.append(cloud.rgb)
        samples.proprio.append(proprio_vector(ep.robot.gripper_command[frame] > 0, fingers[frame], k))
        samples.target_position.append(np.asarray(target.position, np.float32))
        samples.target_quaternion.append(np.asarray(target.quaternion, np.float64))
        samples.target_gripper_open.append(target.gripper_open)
        samples.target_ignore_collisions.append(target.ignore_collisions)
        samples.task_index.append(0)
        samples.instruction_index.append(0)
        samples.episode_index.append(0)
        samples.keyframe_start.append(frame in starts)
        samples.keyframe_index.append(k)
        samples.final_keyframe.append(k == len(annotation.keyframes) - 1)
    return samples


def variation_phrasings(samples: SampleSet) -> list[list[str]]:
    """Each of the sample set's instructions as the trained phrasings of its variation, the first template's
    first (`Task.phrasings`); an instruction of no known task or variation as its own words alone."""
    from rvt2cli.tasks import all_tasks

    known = all_tasks()
    task_of = dict(zip(samples.instruction_index, samples.task_index))
    out = []
    for i, text in enumerate(samples.instructions):
        task = known.get(samples.tasks[task_of[i]]) if i in task_of else None
        out.append(task.phrasings(text) if task is not None else [text])
    return out


def trained_instructions(samples: SampleSet, phrasings: str = "demo") -> list[str]:
    """The words a model trained with `--phrasings` reads for each of the sample set's instructions: the demo's
    own ("demo", and "all", whose other phrasings `phrasing_table` adds per draw), or its variation's first
    trained phrasing ("first": RLBench's descriptions[0], the one PerAct, RVT and RVT-2 train on). Training
    and offline scoring both ask here."""
    if phrasings != "first":
        return list(samples.instructions)
    return [own[0] for own in variation_phrasings(samples)]


def phrasing_table(samples: SampleSet) -> tuple[list[str], np.ndarray, np.ndarray]:
    """`rvt2 train --phrasings all`: each instruction of the sample set beside the other trained phrasings of
    its variation (`Task.phrasings`; a task not in tasks/ keeps its own). Returns the instruction table
    extended by the phrasings no demo used (the set's own entries keep their indices), each instruction's
    phrasings as indices into that table [U, K] (-1 past its count), and the counts [U]."""
    texts = list(samples.instructions)
    index = {text: i for i, text in enumerate(texts)}
    rows = []
    for own in variation_phrasings(samples):
        row = []
        for phrasing in own:
            if phrasing not in index:
                index[phrasing] = len(texts)
                texts.append(phrasing)
            row.append(index[phrasing])
        rows.append(row)
    counts = np.array([len(r) for r in rows], np.int64)
    table = np.full((len(rows), int(counts.max(initial=1))), -1, np.int64)
    for i, row in enumerate(rows):
        table[i, :len(row)] = row
    return texts, table, counts


def load_samples(paths: list[Path], include_failures: bool = False, progress: bool = True,
                 keyframe_starts_only: bool = False, cameras: tuple[str, ...] | None = None,
                 tasks: list[str] | None = None, workers: int = 1, handover: str = "files") -> SampleSet:
    """Read every episode's samples (of these tasks only, if given), in the order given, with up to
    `workers` processes (`runtime.map_over_files`; the result is the same). The processes hand their clouds
    over through files, read here in threads (`cloud_spool`), or with `handover="pipe"` through the pool's
    result pipe; the samples are the same. Refuses, in one line, files without keyframes."""
    from rvt2cli.data import topics
    from rvt2cli.data.reader import read_episode_overview

    unannotated, failures, usable = [], [], []
    for path in paths:
        overview = read_episode_overview(path)
        if tasks is not None and overview.meta.task not in tasks:
            continue
        if not overview.meta.success and not include_failures:
            failures.append(path)
        elif topics.KEYFRAMES not in overview.topics:
            unannotated.append(path)
        else:
            usable.append(path)
    if unannotated:
        names = ", ".join(str(p) for p in unannotated[:3]) + (f" (+{len(unannotated) - 3} more)" if len(unannotated) > 3 else "")
        folder = unannotated[0].parent
        raise UserError(f"{names}: no keyframes; run `rvt2 extract-keyframes {folder}/` first")
    samples = SampleSet()
    bar = tqdm(total=len(usable), desc="load samples", unit="ep", disable=not progress)
    if handover == "files" and runtime.file_workers(workers, len(usable)) > 1:
        for part in _parts_through_files(usable, keyframe_starts_only, cameras, workers):
            samples.extend(part)
            bar.update()
    else:
        for part in runtime.map_over_files(episode_samples, usable, keyframe_starts_only, cameras, workers=workers):
            samples.extend(part)
            bar.update()
    bar.close()
    if len(samples) == 0:
        raise UserError(f"no training samples in {len(paths)} file(s)" + (f" ({len(failures)} failed episodes skipped)" if failures else "")
                        + (f" of the tasks {', '.join(tasks)}" if tasks is not None else ""))
    samples.skipped_failures = len(failures)
    return samples


def _samples_clouds_spooled(path: Path, keyframe_starts_only: bool, cameras, spool: str) -> tuple[SampleSet, SpooledClouds | None]:
    """`episode_samples` in a reader process, its clouds written to a file of `spool` (None: they stay in the set)."""
    part = episode_samples(path, keyframe_starts_only, cameras)
    if (spooled := spool_clouds(part.xyz, part.rgb, spool)) is None:
        return part, None
    part.xyz, part.rgb = [], []
    return part, spooled


def _parts_through_files(paths: list[Path], keyframe_starts_only: bool, cameras, workers: int):
    """Each episode's samples, in order, the clouds read back from the readers' files by a few threads at once."""
    threads = max(2, min(8, runtime.usable_cores() // 4))
    with spool_folder() as spool, ThreadPoolExecutor(threads) as receivers:
        def receive(part, spooled):
            if spooled is not None:
                part.xyz, part.rgb = unspool_clouds(spooled)
            return part

        in_flight = deque()
        for part, spooled in runtime.map_over_files(_samples_clouds_spooled, paths, keyframe_starts_only, cameras, spool,
                                                    workers=workers):
            in_flight.append(receivers.submit(receive, part, spooled))
            while len(in_flight) > 2 * threads or (in_flight and in_flight[0].done()):
                yield in_flight.popleft().result()
        while in_flight:
            yield in_flight.popleft().result()


def select_samples(samples: SampleSet, episodes_per_task: int | None = None, keyframe_starts_only: bool = False) -> list[int]:
    """Indices of the samples to train on: those of each task's first `episodes_per_task` episodes (in
    file-name order, i.e. the lowest seeds) and, with `keyframe_starts_only`, only the samples observed
    at frame 0 or at a keyframe (the states a closed-loop keyframe policy is in), not in-between ones."""
    keep_episodes = None
    if episodes_per_task is not None:
        by_task: dict[int, list[int]] = {}
        for e, t in sorted(set(zip(samples.episode_index, samples.task_index)), key=lambda et: samples.episodes[et[0]]):
            by_task.setdefault(t, []).append(e)
        short = [samples.tasks[t] for t, eps in by_task.items() if len(eps) < episodes_per_task]
        if short:
            raise UserError(f"--episodes-per-task {episodes_per_task}: task(s) {', '.join(short)} have fewer episodes; "
                            f"record more or lower the number")
        keep_episodes = {e for eps in by_task.values() for e in eps[:episodes_per_task]}
    return [i for i in range(len(samples))
            if (keep_episodes is None or samples.episode_index[i] in keep_episodes)
            and (not keyframe_starts_only or samples.keyframe_start[i])]
