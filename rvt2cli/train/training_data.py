"""The samples a run trains on: read from episodes or a sample cache, selected (--episodes-per-task,
--keyframe-starts-only, --task-set), split into training and held-out episodes, their instructions
embedded, and packed (rvt2cli.train.batches). `rvt2cli.train.data_sharing` hands them to every process
of a several-GPU run.
"""

import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from rvt2cli.data.paths import episode_paths
from rvt2cli.errors import UserError
from rvt2cli.model.config import ModelConfig
from rvt2cli.model.language import InstructionCache
from rvt2cli.runtime import usable_cores
from rvt2cli.tasks import aim_offsets, tasks_of_set
from rvt2cli.train.batches import TaskSampler
from rvt2cli.train.checkpoint import Checkpoint
from rvt2cli.train.clouds import clouds_bytes, clouds_on_host
from rvt2cli.train.options import TrainOptions
from rvt2cli.train.packed import PackedSamples, pack
from rvt2cli.train.sample_cache import is_sample_cache, load_sample_cache
from rvt2cli.train.samples import SampleSet, load_samples, phrasing_table, select_samples, trained_instructions


def load_training_data(data: list[str], include_failures: bool, progress: bool, keyframe_starts_only: bool = False,
                       cameras: tuple[str, ...] | None = None, task_set: str | None = None
                       ) -> tuple[SampleSet, dict[str, torch.Tensor]]:
    """Samples from one sample cache (with its instruction embeddings) or from episode files (embeddings
    still to compute; with `keyframe_starts_only`, the other samples' clouds are not even fused; with
    `task_set`, only the episodes of that set's tasks)."""
    tasks = tasks_of_set(task_set) if task_set else None
    caches = [d for d in data if is_sample_cache(d)]
    if caches:
        if len(data) > 1:
            raise UserError(f"--data: give one sample cache ({caches[0]}) or episode files/folders, not both")
        samples, embeddings = load_sample_cache(caches[0])
        if tasks is not None and not set(samples.tasks) <= set(tasks):
            raise UserError(f"{caches[0]}: holds tasks outside --task-set {task_set} "
                            f"({', '.join(sorted(set(samples.tasks) - set(tasks)))}); pack a cache of the set's episodes")
        if cameras and any(list(cameras) != r["cameras"] for r in samples.rigs.values()):
            raise UserError(f"{caches[0]}: its clouds were fused from other cameras than --cameras {','.join(cameras)}; "
                            f"pack the cache with `rvt2 pack-samples --cameras {','.join(cameras)}`")
        return samples, embeddings
    paths = episode_paths(data)
    # one process reads the episodes, with all the cores (a several-GPU run passes the result on: `data_sharing.load_data`)
    return load_samples(paths, include_failures, progress=progress, keyframe_starts_only=keyframe_starts_only,
                        cameras=cameras, tasks=tasks, workers=usable_cores()), {}


def split_episodes(samples, val_episodes: int, selected: list[int] | None = None) -> tuple[list[int], list[int]]:
    """Hold out the last `val_episodes` episodes of every task that has at least 3 (among the selected samples)."""
    selected = list(range(len(samples))) if selected is None else selected
    episode_task = {}
    for i in selected:
        episode_task[samples.episode_index[i]] = samples.task_index[i]
    held = set()
    for t in set(episode_task.values()):
        episodes = sorted(e for e, et in episode_task.items() if et == t)
        if len(episodes) >= 3 and val_episodes > 0:
            held.update(episodes[-val_episodes:])
    train = [i for i in selected if samples.episode_index[i] not in held]
    val = [i for i in selected if samples.episode_index[i] in held]
    return train, val


@dataclass
class TrainingData:
    samples: SampleSet          # tables and per-sample columns; its clouds are dropped once packed
    selected: list[int]         # the samples trained or validated on (indices into `samples`)
    packed: PackedSamples
    packed_val: PackedSamples | None
    instructions: InstructionCache
    aim_offsets: dict[str, list[float]] | None = None   # what the targets aim at (--aim-held), per task
    task_weights: np.ndarray | None = None   # per task index (--task-weights); None: tasks drawn uniformly


def read_data(opts: TrainOptions, cfg: ModelConfig, device, progress: bool, resume: Checkpoint | None, say) -> TrainingData:
    """Read, select, split, embed and pack the training samples (`data_sharing.load_data` without the sharing)."""
    started = time.perf_counter()
    samples, known = load_training_data(opts.data, opts.include_failures, progress, opts.keyframe_starts_only, opts.cameras,
                                        opts.task_set)
    selected = select_samples(samples, opts.episodes_per_task, opts.keyframe_starts_only)
    train_idx, val_idx = split_episodes(samples, opts.val_episodes, selected)
    if not train_idx:
        raise UserError(f"--data: no training samples left after holding out {opts.val_episodes} episode(s) per task; "
                        f"lower --val-episodes")
    known = {text: emb[: cfg.lang_tokens] for text, emb in known.items()}  # a cache stores the longest prefix any config uses
    if resume:
        known = {**known, **resume.instruction_embeddings}
    cache = InstructionCache(cfg.lang_tokens, known)
    phrasings = None
    if opts.phrasings == "all":
        texts, table, counts = phrasing_table(samples)
        lang, phrasings = cache(texts), (table, counts)
        say(f"phrasings: {len(texts)} instructions for the {len(samples.instructions)} the demos use "
            f"(--phrasings all: up to {table.shape[1]} per variation)")
    else:
        texts = trained_instructions(samples, opts.phrasings)
        lang = cache(texts)
        if opts.phrasings == "first":
            say(f"phrasings: {len(set(texts))} instructions, each variation's first, for the {len(samples.instructions)} "
                "the demos use (--phrasings first)")
    aims = None
    if opts.aim_held:  # a resumed run keeps the offsets it began with, whatever tasks/*.toml says now
        aims = resume.aim_offsets if resume is not None and resume.aim_offsets is not None else aim_offsets(samples.tasks)
    if aims == {}:
        raise UserError(f"--aim-held: none of the tasks ({', '.join(samples.tasks)}) declares an aim_offset in its "
                        "tasks/*.toml; add one (m, in the TCP frame) or leave the flag out")
    weights = task_weight_array(opts.task_weights, samples.tasks)
    read_seconds = time.perf_counter() - started
    nbytes = clouds_bytes(len(train_idx) + len(val_idx), opts.max_points)
    on_host = clouds_on_host(opts.samples_on, nbytes, device)
    packed = pack(samples, train_idx, lang, opts.max_points, device, seed=opts.seed, aim_offsets=aims, phrasings=phrasings,
                  clouds_on_host=on_host)
    packed_val = pack(samples, val_idx, lang, opts.max_points, device, seed=opts.seed, aim_offsets=aims,
                      clouds_on_host=on_host) if val_idx else None
    pack_seconds = time.perf_counter() - started - read_seconds
    used_episodes = len({samples.episode_index[i] for i in selected})
    say(f"data: {len(selected)} samples from {used_episodes} episodes of {len(samples.tasks)} task(s) "
        f"({', '.join(samples.tasks)}); {len(train_idx)} train, {len(val_idx)} validation"
        + (f"; skipped {samples.skipped_empty} empty clouds" if samples.skipped_empty else "")
        + (f", {samples.skipped_failures} failed episodes" if samples.skipped_failures else "")
        + f"; clouds {f'{nbytes / 2**30:.1f} GiB' if nbytes >= 2**30 else f'{nbytes / 2**20:.0f} MiB'} on the "
        + ("host" if on_host else "GPU" if device.type == "cuda" else "CPU")
        + f" (read and embedded in {read_seconds:.0f} s, packed in {pack_seconds:.0f} s)")
    if weights is not None:
        shares = TaskSampler(packed.task, task_weights=weights).shares()
        say("task shares of the draws (--task-weights): "
            + ", ".join(f"{samples.tasks[t]} {share:.0%}" for t, share in zip(np.unique(packed.task), shares)))
    # the fused clouds as read are packed now: only the packed ones are trained on (rvt2-18: tens of GiB of host memory)
    samples = replace(samples, xyz=[], rgb=[])
    return TrainingData(samples, selected, packed, packed_val, cache, aims, weights)


def task_weight_array(task_weights: dict[str, float] | None, tasks: list[str]) -> np.ndarray | None:
    """`--task-weights` as one weight per task index (tasks it leaves out: 1); None: draw tasks uniformly."""
    if task_weights is None:
        return None
    unknown = sorted(set(task_weights) - set(tasks))
    if unknown:
        raise UserError(f"--task-weights: no {', '.join(unknown)} in --data (its tasks: {', '.join(tasks)}); "
                        "name tasks the data holds")
    return np.array([task_weights.get(task, 1.0) for task in tasks], np.float64)
