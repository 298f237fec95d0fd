"""Training batches from the packed samples (rvt2cli.train.packed): sampling task by task, augmentation,
and the tensors the step takes. The clouds live on the training device or on the host
(rvt2cli.train.clouds); everything else a batch needs is small. A batch is drawn first (`draw_batch`:
its samples and every random number of its augmentation, in one order) and made on the device after
(`assemble`), whole or a part at a time (`--micro-batch`: the parts of one draw are the rows of the whole
batch). A batch's small host-side arrays (indices, targets, augmentation) reach the GPU through pinned
memory without blocking the host, so the host prepares the next batch while the GPU still runs the
current step.
"""

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from rvt2cli.model.config import ModelConfig
from rvt2cli.model.observation import Observation, aim_vector, aimed_target, colours
from rvt2cli.model.rotation import euler_to_bins, quaternion_to_euler
from rvt2cli.train.augment import augment_points, augment_targets, sample_augmentation, yaw_matrices
from rvt2cli.train.cloud_shards import ShardedRows
from rvt2cli.train.clouds import StagedRows, host_rows
from rvt2cli.train.packed import PackedSamples


class TaskSampler:
    """Draw a task, then one of its samples uniformly; with `start_share` > 0, that share of the draws
    takes one of the task's keyframe-start samples instead.

    Tasks are drawn uniformly, as the paper does, or in proportion to `task_weights` (one per task
    index; `rvt2 train --task-weights`): with one model and a fixed number of steps, a task's precision
    follows the samples it is trained on (insert_peg's insertion: 9.0 mm and 3.3 degrees off in results
    v8's 8-task model, 5.1 mm and 1.0 degree trained alone for the same 1,200 steps in v9), and the tasks already
    solved need fewer.

    Why the starts: a closed loop only ever observes the scene at keyframe starts (frame 0, then where
    each keyframe was reached), but the samples between keyframes (every `--obs-every` frames, the
    paper's demo augmentation) outnumber them 3-5 to 1, and are the easy ones: mid-motion, the gripper
    already points where it goes. A long transit (insert_peg's grasp to pre-insert) leaves its one start
    sample, the only one a rollout asks about, a twentieth of the task's draws. Measured
    (docs/RESULTS.md v6): a share of 0.5 left that start's error where it was (61 mm); the sampling is
    not what limits it."""

    def __init__(self, task: np.ndarray, start: np.ndarray | None = None, start_share: float = 0.0,
                 task_weights: np.ndarray | None = None):
        if not 0.0 <= start_share <= 1.0:
            raise ValueError("start_share must be within [0, 1]")
        present = np.unique(task)
        self.by_task = [np.flatnonzero(task == t) for t in present]
        start = np.zeros(len(task), bool) if start is None else np.asarray(start, bool)
        self.starts_by_task = [indices[start[indices]] for indices in self.by_task]
        self.start_share = start_share
        self.weights = None
        if task_weights is not None:
            w = np.asarray(task_weights, np.float64)[present]
            if not (np.isfinite(w).all() and (w > 0).all()):
                raise ValueError("task weights must be finite and positive")
            self.weights = torch.from_numpy(w / w.sum())

    def shares(self) -> np.ndarray:
        """Each present task's expected share of the draws, in task-index order."""
        n = len(self.by_task)
        return np.full(n, 1.0 / n) if self.weights is None else self.weights.numpy().copy()

    def sample(self, n: int, generator: torch.Generator) -> np.ndarray:
        if self.weights is None:  # uniform: the random numbers every earlier run drew
            tasks = torch.randint(len(self.by_task), (n,), generator=generator).numpy()
        else:
            tasks = torch.multinomial(self.weights, n, replacement=True, generator=generator).numpy()
        picks = torch.rand(n, generator=generator, dtype=torch.float64).numpy()
        from_starts = np.zeros(n, bool)
        if self.start_share > 0:  # only then: a run without it draws exactly the random numbers it always did
            from_starts = torch.rand(n, generator=generator, dtype=torch.float64).numpy() < self.start_share
        pools = [self.starts_by_task[t] if start and len(self.starts_by_task[t]) else self.by_task[t]
                 for t, start in zip(tasks, from_starts)]
        return np.array([pool[int(p * len(pool))] for pool, p in zip(pools, picks)])


@dataclass
class Batch:
    obs: Observation
    position: torch.Tensor       # [B, 3] cube coordinates of the aim's target (the TCP's without an aim)
    tcp_position: torch.Tensor   # [B, 3] cube coordinates of the TCP's target
    rot_bins: torch.Tensor       # [B, 3]
    euler_deg: torch.Tensor      # [B, 3] the target's Euler angles (soft rotation targets)
    gripper: torch.Tensor        # [B]
    collision: torch.Tensor      # [B]
    quaternion: np.ndarray       # [B, 4] the (augmented) target orientation
    half: np.ndarray             # [B] metres per cube unit
    stage2_center: torch.Tensor | None = None


def to_device(array: np.ndarray, device: torch.device) -> torch.Tensor:
    """A host array on the device; to a GPU through pinned memory, without waiting for it."""
    tensor = torch.from_numpy(np.ascontiguousarray(array))
    if device.type != "cuda":
        return tensor
    return tensor.pin_memory().to(device, non_blocking=True)


@dataclass
class Draw:
    """A batch's samples and every random number its making takes: all that the seed decides."""
    idx: np.ndarray                      # [B] rows of the packed samples
    yaw: np.ndarray | None = None        # [B] rad, the augmentation (None: not augmented, a validation batch)
    shift: np.ndarray | None = None      # [B, 3] m
    phrasing: np.ndarray | None = None   # [B] in [0, 1): which of its phrasings a sample reads (--phrasings all)
    noise: np.ndarray | None = None      # [B, 3] m, the stage-2 centre's offset from the target

    def __len__(self) -> int:
        return len(self.idx)

    def part(self, rows: slice) -> "Draw":
        """These rows of the batch: the same samples and random numbers as in the whole."""
        return Draw(*(None if a is None else a[rows] for a in (self.idx, self.yaw, self.shift, self.phrasing, self.noise)))


def draw_batch(packed: PackedSamples, idx: np.ndarray, cfg: ModelConfig, generator: torch.Generator,
               max_translation: float = 0.125, max_yaw_deg: float = 45.0) -> Draw:
    """A training batch's random numbers for samples `idx`, drawn from `generator` in one fixed order."""
    yaw, shift = sample_augmentation(len(idx), generator, max_translation, max_yaw_deg)
    phrasing = noise = None
    if packed.phrasings is not None:
        phrasing = torch.rand(len(idx), generator=generator, dtype=torch.float64).numpy()
    if cfg.stages == 2:
        noise = (torch.rand(len(idx), 3, generator=generator, dtype=torch.float64).numpy() * 2 - 1) * cfg.stage2_noise
    return Draw(np.asarray(idx), yaw, shift, phrasing, noise)


def assemble(packed: PackedSamples, draw: Draw, cfg: ModelConfig, rows=None) -> Batch:
    """The batch `draw` describes, on the packed samples' device. `rows` brings host-resident clouds there
    (`StagedRows`, `ShardedRows`; default: through freshly pinned memory)."""
    device, idx = packed.device, draw.idx
    tasks = packed.task[idx]
    center, half, lo, hi = packed.center[tasks], packed.half[tasks], packed.lo[tasks], packed.hi[tasks]
    position, quaternion = packed.target_position[idx], packed.target_quaternion[idx]
    aim = None if packed.aim_offset is None else aim_vector(torch.from_numpy(packed.aim_offset[tasks]),
                                                            torch.from_numpy(packed.gripper_open[idx]), torch.from_numpy(half)).numpy()
    if aim is not None:  # the target is where the aim goes, rigidly attached to the TCP's: augmented alike
        position = aimed_target(position, quaternion, aim * half[:, None])
    index = to_device(np.asarray(idx, np.int64), device)
    if not packed.clouds_on_host:
        xyz, rgb = packed.xyz[index], packed.rgb[index]
    elif rows is not None:
        xyz, rgb = rows(idx)
    else:
        xyz, rgb = host_rows(packed.xyz, packed.rgb, packed.cloud_rows(idx), device)
    center_t = to_device(center.astype(np.float32), device)
    if draw.yaw is not None:
        position, quaternion, yaw, shift = augment_targets(position, quaternion, center, lo, hi, draw.yaw, draw.shift)
        xyz = augment_points(xyz, center_t, to_device(yaw_matrices(yaw).astype(np.float32), device),
                             to_device(shift.astype(np.float32), device))
    tcp = position if aim is None else aimed_target(position, quaternion, -aim * half[:, None])
    half_t = to_device(half.astype(np.float32), device)[:, None, None]
    points = (xyz - center_t[:, None]) / half_t
    instruction = packed.instruction[index]
    if draw.phrasing is not None:  # one of each sample's phrasings, uniformly
        choice = (to_device(draw.phrasing, device) * packed.phrasing_count[instruction]).long()
        instruction = packed.phrasings[instruction, choice]
    obs = Observation(points=points, rgb=colours(rgb), num_points=packed.count[index],
                      proprio=packed.proprio[index], lang=packed.lang[instruction],
                      aim=None if aim is None else to_device(aim, device))
    position_cube = ((position - center) / half[:, None]).astype(np.float32)
    euler = quaternion_to_euler(quaternion)
    batch = Batch(obs=obs, position=to_device(position_cube, device),
                  tcp_position=to_device(((tcp - center) / half[:, None]).astype(np.float32), device),
                  rot_bins=to_device(euler_to_bins(euler, cfg.rotation_bins), device),
                  euler_deg=to_device(euler.astype(np.float32), device),
                  gripper=to_device(packed.target_gripper[idx], device),
                  collision=to_device(packed.target_collision[idx], device),
                  quaternion=quaternion, half=half)
    if draw.noise is not None and cfg.stages == 2:
        batch.stage2_center = to_device((position_cube + (draw.noise / half[:, None]).astype(np.float32)), device)
    return batch


def make_batch(packed: PackedSamples, idx: np.ndarray, cfg: ModelConfig, generator: torch.Generator | None = None,
               max_translation: float = 0.125, max_yaw_deg: float = 45.0) -> Batch:
    """A batch of samples `idx`; with a generator, augmented and with a noisy stage-2 centre (training)."""
    draw = Draw(np.asarray(idx)) if generator is None else draw_batch(packed, idx, cfg, generator, max_translation, max_yaw_deg)
    return assemble(packed, draw, cfg)


class MicroBatches(Sequence):
    """One drawn batch made a part at a time (`--micro-batch`), each part when it is reached, so that only
    one part's clouds and activations are on the GPU at once; their losses, weighted by their share of
    the rows, add up to the whole batch's."""

    def __init__(self, make, draw: Draw, size: int):
        self.make, self.total = make, len(draw)
        self.parts = [draw.part(slice(start, start + size)) for start in range(0, len(draw), size)]
        self.first = make(self.parts[0])   # made now, as a whole batch would be (the loop makes it a step ahead)

    def __len__(self) -> int:
        return len(self.parts)

    def __getitem__(self, i: int) -> Batch:
        if not 0 <= i < len(self.parts):
            raise IndexError(i)
        return self.first if i == 0 else self.make(self.parts[i])

    def weight(self, i: int) -> float:
        return len(self.parts[i]) / self.total


class BatchStream:
    """The training loop's batches, in order: samples drawn task by task (`TaskSampler`), augmented, on
    the device (what `rvt2 train` runs and `benchmarks/loop_bench.py` times); with `micro_batch` smaller
    than `batch_size`, each as `MicroBatches` of the same draw. Making one costs the host about a
    millisecond at batch 192 (H200 machine), so it is made in turn: a thread preparing batches ahead
    measured no faster; host-resident clouds add their rows' gather (`clouds.StagedRows`)."""

    def __init__(self, packed: PackedSamples, cfg: ModelConfig, generator: torch.Generator, batch_size: int,
                 augment: bool = True, start_share: float = 0.0, task_weights: np.ndarray | None = None,
                 micro_batch: int | None = None):
        self.packed, self.cfg, self.generator, self.batch_size = packed, cfg, generator, batch_size
        self.max_translation, self.max_yaw_deg = (0.125, 45.0) if augment else (0.0, 0.0)
        self.sampler = TaskSampler(packed.task, packed.keyframe_start, start_share, task_weights)
        self.micro_batch = micro_batch if micro_batch and micro_batch < batch_size else None
        rows = self.micro_batch or batch_size
        self.rows = None
        if packed.shard is not None:
            self.rows = ShardedRows(packed.xyz, packed.rgb, *packed.shard, packed.device, rows)
        elif packed.clouds_on_host:
            self.rows = StagedRows(packed.xyz, packed.rgb, packed.device, rows)

    def __iter__(self):
        return self

    def draw(self) -> Draw:
        return draw_batch(self.packed, self.sampler.sample(self.batch_size, self.generator), self.cfg, self.generator,
                          self.max_translation, self.max_yaw_deg)

    def make(self, draw: Draw) -> Batch:
        return assemble(self.packed, draw, self.cfg, self.rows)

    def __next__(self) -> Batch | MicroBatches:
        draw = self.draw()
        return self.make(draw) if self.micro_batch is None else MicroBatches(self.make, draw, self.micro_batch)
