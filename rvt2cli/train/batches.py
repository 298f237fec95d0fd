"""Samples packed into tensors (on the training device), task-uniform sampling, and batches.

Clouds are padded (or randomly subsampled) to `max_points` so every batch has the same shape; the
renderer ignores the padding through `num_points`.
"""

from dataclasses import dataclass

import numpy as np
import torch

from rvt2cli.model.config import ModelConfig
from rvt2cli.model.policy import Observation
from rvt2cli.model.rotation import quaternion_to_bins
from rvt2cli.model.workspace import Workspace
from rvt2cli.train.augment import augment_points, augment_targets, sample_augmentation
from rvt2cli.train.samples import SampleSet


@dataclass
class PackedSamples:
    xyz: torch.Tensor          # [S, N, 3] float32, world frame
    rgb: torch.Tensor          # [S, N, 3] uint8
    count: torch.Tensor        # [S]
    proprio: torch.Tensor      # [S, P]
    instruction: torch.Tensor  # [S] index into lang
    lang: torch.Tensor         # [U, L, 384]
    task: np.ndarray           # [S]
    target_position: np.ndarray    # [S, 3] world
    target_quaternion: np.ndarray  # [S, 4] xyzw
    target_gripper: np.ndarray     # [S] 1 = open
    target_collision: np.ndarray   # [S] 1 = ignore collisions
    center: np.ndarray         # [T, 3] workspace centre per task
    half: np.ndarray           # [T] workspace half extent per task
    lo: np.ndarray             # [T, 3] scene bounds per task
    hi: np.ndarray

    def __len__(self) -> int:
        return len(self.count)


def pack(samples: SampleSet, indices: list[int], lang: torch.Tensor, max_points: int, device, seed: int = 0) -> PackedSamples:
    rng = np.random.default_rng(seed)
    n = len(indices)
    xyz = np.zeros((n, max_points, 3), np.float32)
    rgb = np.zeros((n, max_points, 3), np.uint8)
    count = np.zeros(n, np.int64)
    for row, i in enumerate(indices):
        points, colours = samples.xyz[i], samples.rgb[i]
        if len(points) > max_points:
            keep = np.sort(rng.choice(len(points), max_points, replace=False))
            points, colours = points[keep], colours[keep]
        xyz[row, : len(points)], rgb[row, : len(points)], count[row] = points, colours, len(points)
    workspaces = [Workspace.from_bounds(samples.bounds[t]) for t in samples.tasks]
    pick = np.asarray(indices, dtype=np.int64)
    return PackedSamples(
        xyz=torch.from_numpy(xyz).to(device), rgb=torch.from_numpy(rgb).to(device), count=torch.from_numpy(count).to(device),
        proprio=torch.from_numpy(np.stack([samples.proprio[i] for i in indices])).to(device),
        instruction=torch.as_tensor([samples.instruction_index[i] for i in indices], device=device),
        lang=lang.to(device),
        task=np.asarray(samples.task_index)[pick],
        target_position=np.stack([samples.target_position[i] for i in indices]).astype(np.float64),
        target_quaternion=np.stack([samples.target_quaternion[i] for i in indices]),
        target_gripper=np.asarray(samples.target_gripper_open, np.int64)[pick],
        target_collision=np.asarray(samples.target_ignore_collisions, np.int64)[pick],
        center=np.array([w.center for w in workspaces]), half=np.array([w.half_extent for w in workspaces]),
        lo=np.array([samples.bounds[t][:3] for t in samples.tasks]), hi=np.array([samples.bounds[t][3:] for t in samples.tasks]),
    )


class TaskUniformSampler:
    """Draw a task uniformly, then one of its samples uniformly."""

    def __init__(self, task: np.ndarray):
        self.by_task = [np.flatnonzero(task == t) for t in np.unique(task)]

    def sample(self, n: int, generator: torch.Generator) -> np.ndarray:
        tasks = torch.randint(len(self.by_task), (n,), generator=generator).numpy()
        picks = torch.rand(n, generator=generator, dtype=torch.float64).numpy()
        return np.array([self.by_task[t][int(p * len(self.by_task[t]))] for t, p in zip(tasks, picks)])


@dataclass
class Batch:
    obs: Observation
    position: torch.Tensor       # [B, 3] cube coordinates
    rot_bins: torch.Tensor       # [B, 3]
    gripper: torch.Tensor        # [B]
    collision: torch.Tensor      # [B]
    quaternion: np.ndarray       # [B, 4] the (augmented) target orientation
    half: np.ndarray             # [B] metres per cube unit
    stage2_center: torch.Tensor | None = None


def make_batch(packed: PackedSamples, idx: np.ndarray, cfg: ModelConfig, generator: torch.Generator | None = None,
               max_translation: float = 0.125, max_yaw_deg: float = 45.0) -> Batch:
    """A batch of samples `idx`; with a generator, augmented and with a noisy stage-2 centre (training)."""
    device = packed.xyz.device
    tasks = packed.task[idx]
    center, half, lo, hi = packed.center[tasks], packed.half[tasks], packed.lo[tasks], packed.hi[tasks]
    position, quaternion = packed.target_position[idx], packed.target_quaternion[idx]
    xyz = packed.xyz[torch.as_tensor(idx, device=device)]
    center_t = torch.as_tensor(center, dtype=torch.float32, device=device)
    if generator is not None:
        yaw, shift = sample_augmentation(len(idx), generator, max_translation, max_yaw_deg)
        position, quaternion, yaw, shift = augment_targets(position, quaternion, center, lo, hi, yaw, shift)
        xyz = augment_points(xyz, center_t, yaw, shift)
    half_t = torch.as_tensor(half, dtype=torch.float32, device=device)[:, None, None]
    points = (xyz - center_t[:, None]) / half_t
    index = torch.as_tensor(idx, device=device)
    obs = Observation(points=points, rgb=packed.rgb[index].float() / 255.0, num_points=packed.count[index],
                      proprio=packed.proprio[index], lang=packed.lang[packed.instruction[index]])
    position_cube = torch.as_tensor((position - center) / half[:, None], dtype=torch.float32, device=device)
    batch = Batch(obs=obs, position=position_cube,
                  rot_bins=torch.as_tensor(quaternion_to_bins(quaternion, cfg.rotation_bins), device=device),
                  gripper=torch.as_tensor(packed.target_gripper[idx], device=device),
                  collision=torch.as_tensor(packed.target_collision[idx], device=device),
                  quaternion=quaternion, half=half)
    if generator is not None and cfg.stages == 2:
        noise = (torch.rand(len(idx), 3, generator=generator, dtype=torch.float64).numpy() * 2 - 1) * cfg.stage2_noise
        batch.stage2_center = position_cube + torch.as_tensor(noise / half[:, None], dtype=torch.float32, device=device)
    return batch
