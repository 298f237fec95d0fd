"""Samples packed into tensors (on the training device), sampling task by task, and batches.

Clouds are padded (or randomly subsampled) to `max_points` so every batch has the same shape; the
renderer ignores the padding through `num_points`. A batch's small host-side arrays (indices,
targets, augmentation) reach the GPU through pinned memory without blocking the host, so the host
prepares the next batch while the GPU still runs the current step.
"""

from dataclasses import dataclass

import numpy as np
import torch

from rvt2cli.model.config import ModelConfig
from rvt2cli.model.observation import Observation, aim_vector, aimed_target, colours, fit_points
from rvt2cli.model.rotation import euler_to_bins, quaternion_to_euler
from rvt2cli.render.workspace import Workspace
from rvt2cli.tasks import TCP_AIM
from rvt2cli.train.augment import augment_points, augment_targets, sample_augmentation, yaw_matrices
from rvt2cli.train.samples import SampleSet


@dataclass
class PackedSamples:
    xyz: torch.Tensor          # [S, N, 3] float32, world frame
    rgb: torch.Tensor          # [S, N, 3] uint8
    count: torch.Tensor        # [S]
    proprio: torch.Tensor      # [S, P]
    instruction: torch.Tensor  # [S] index into lang
    lang: torch.Tensor         # [U, L, LANG_DIM]
    task: np.ndarray           # [S]
    keyframe_index: np.ndarray  # [S] which keyframe of its episode the target is (-1: unknown)
    final_keyframe: np.ndarray  # [S] bool: the target is its episode's last keyframe
    keyframe_start: np.ndarray  # [S] bool: observed at frame 0 or at a keyframe (what a closed loop sees)
    target_position: np.ndarray    # [S, 3] world
    target_quaternion: np.ndarray  # [S, 4] xyzw
    target_gripper: np.ndarray     # [S] 1 = open
    target_collision: np.ndarray   # [S] 1 = ignore collisions
    center: np.ndarray         # [T, 3] workspace centre per task
    half: np.ndarray           # [T] workspace half extent per task
    lo: np.ndarray             # [T, 3] scene bounds per task
    hi: np.ndarray
    gripper_open: np.ndarray   # [S] bool: the gripper at the observation (proprio)
    aim_offset: np.ndarray | None = None  # [T, 3] m, TCP frame, per task (rvt2 train --aim-held); None: the TCP
    phrasings: torch.Tensor | None = None       # [U, K] each instruction's phrasings, indices into lang
    phrasing_count: torch.Tensor | None = None  # [U] (rvt2 train --phrasings all; `samples.phrasing_table`)

    def __len__(self) -> int:
        return len(self.count)


def pack(samples: SampleSet, indices: list[int], lang: torch.Tensor, max_points: int, device, seed: int = 0,
         aim_offsets: dict[str, list[float]] | None = None,
         phrasings: tuple[np.ndarray, np.ndarray] | None = None) -> PackedSamples:
    """`aim_offsets`: task -> aim offset (m, TCP frame) of a policy trained with them (tasks left out: none).
    `phrasings`: each instruction's phrasings and their count (`samples.phrasing_table`), drawn from in
    training batches."""
    rng = np.random.default_rng(seed)
    n = len(indices)
    xyz = np.zeros((n, max_points, 3), np.float32)
    rgb = np.zeros((n, max_points, 3), np.uint8)
    count = np.zeros(n, np.int64)
    for row, i in enumerate(indices):
        xyz[row], rgb[row], count[row] = fit_points(samples.xyz[i], samples.rgb[i], max_points, rng)
    workspaces = [Workspace.from_bounds(samples.bounds[t]) for t in samples.tasks]
    pick = np.asarray(indices, dtype=np.int64)
    keyframe_index = np.asarray(samples.keyframe_index if samples.keyframe_index else [-1] * len(samples), np.int64)
    final_keyframe = np.asarray(samples.final_keyframe if samples.final_keyframe else [False] * len(samples), bool)
    keyframe_start = np.asarray(samples.keyframe_start if samples.keyframe_start else [False] * len(samples), bool)
    return PackedSamples(
        xyz=torch.from_numpy(xyz).to(device), rgb=torch.from_numpy(rgb).to(device), count=torch.from_numpy(count).to(device),
        proprio=torch.from_numpy(np.stack([samples.proprio[i] for i in indices])).to(device),
        instruction=torch.as_tensor([samples.instruction_index[i] for i in indices], device=device),
        lang=lang.to(device),
        task=np.asarray(samples.task_index)[pick],
        keyframe_index=keyframe_index[pick],
        final_keyframe=final_keyframe[pick],
        keyframe_start=keyframe_start[pick],
        target_position=np.stack([samples.target_position[i] for i in indices]).astype(np.float64),
        target_quaternion=np.stack([samples.target_quaternion[i] for i in indices]),
        target_gripper=np.asarray(samples.target_gripper_open, np.int64)[pick],
        target_collision=np.asarray(samples.target_ignore_collisions, np.int64)[pick],
        center=np.array([w.center for w in workspaces]), half=np.array([w.half_extent for w in workspaces]),
        lo=np.array([samples.bounds[t][:3] for t in samples.tasks]), hi=np.array([samples.bounds[t][3:] for t in samples.tasks]),
        gripper_open=np.array([samples.proprio[i][0] > 0.5 for i in indices], bool),
        aim_offset=None if aim_offsets is None else np.array([aim_offsets.get(t, TCP_AIM) for t in samples.tasks], np.float64),
        phrasings=None if phrasings is None else torch.from_numpy(phrasings[0]).to(device),
        phrasing_count=None if phrasings is None else torch.from_numpy(phrasings[1]).to(device),
    )


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


def make_batch(packed: PackedSamples, idx: np.ndarray, cfg: ModelConfig, generator: torch.Generator | None = None,
               max_translation: float = 0.125, max_yaw_deg: float = 45.0) -> Batch:
    """A batch of samples `idx`; with a generator, augmented and with a noisy stage-2 centre (training)."""
    device = packed.xyz.device
    tasks = packed.task[idx]
    center, half, lo, hi = packed.center[tasks], packed.half[tasks], packed.lo[tasks], packed.hi[tasks]
    position, quaternion = packed.target_position[idx], packed.target_quaternion[idx]
    aim = None if packed.aim_offset is None else aim_vector(torch.from_numpy(packed.aim_offset[tasks]),
                                                            torch.from_numpy(packed.gripper_open[idx]), torch.from_numpy(half)).numpy()
    if aim is not None:  # the target is where the aim goes, rigidly attached to the TCP's: augmented alike
        position = aimed_target(position, quaternion, aim * half[:, None])
    index = to_device(np.asarray(idx, np.int64), device)
    xyz = packed.xyz[index]
    center_t = to_device(center.astype(np.float32), device)
    if generator is not None:
        yaw, shift = sample_augmentation(len(idx), generator, max_translation, max_yaw_deg)
        position, quaternion, yaw, shift = augment_targets(position, quaternion, center, lo, hi, yaw, shift)
        xyz = augment_points(xyz, center_t, to_device(yaw_matrices(yaw).astype(np.float32), device),
                             to_device(shift.astype(np.float32), device))
    tcp = position if aim is None else aimed_target(position, quaternion, -aim * half[:, None])
    half_t = to_device(half.astype(np.float32), device)[:, None, None]
    points = (xyz - center_t[:, None]) / half_t
    instruction = packed.instruction[index]
    if generator is not None and packed.phrasings is not None:  # one of each sample's phrasings, uniformly
        draw = to_device(torch.rand(len(idx), generator=generator, dtype=torch.float64).numpy(), device)
        choice = (draw * packed.phrasing_count[instruction]).long()
        instruction = packed.phrasings[instruction, choice]
    obs = Observation(points=points, rgb=colours(packed.rgb[index]), num_points=packed.count[index],
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
    if generator is not None and cfg.stages == 2:
        noise = (torch.rand(len(idx), 3, generator=generator, dtype=torch.float64).numpy() * 2 - 1) * cfg.stage2_noise
        batch.stage2_center = to_device((position_cube + (noise / half[:, None]).astype(np.float32)), device)
    return batch


class BatchStream:
    """The training loop's batches, in order: samples drawn task by task (`TaskSampler`), augmented, on
    the device (what `rvt2 train` runs and `benchmarks/loop_bench.py` times). Making one costs the host
    about a millisecond at batch 192 (H200 machine), so it is made in turn: a thread preparing batches
    ahead measured no faster."""

    def __init__(self, packed: PackedSamples, cfg: ModelConfig, generator: torch.Generator, batch_size: int,
                 augment: bool = True, start_share: float = 0.0, task_weights: np.ndarray | None = None):
        self.packed, self.cfg, self.generator, self.batch_size = packed, cfg, generator, batch_size
        self.max_translation, self.max_yaw_deg = (0.125, 45.0) if augment else (0.0, 0.0)
        self.sampler = TaskSampler(packed.task, packed.keyframe_start, start_share, task_weights)

    def __iter__(self):
        return self

    def __next__(self) -> Batch:
        return make_batch(self.packed, self.sampler.sample(self.batch_size, self.generator), self.cfg, self.generator,
                          self.max_translation, self.max_yaw_deg)
