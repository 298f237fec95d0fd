"""Training samples packed into tensors: every cloud padded (or randomly subsampled) to `max_points` rows
so that every batch has the same shape (the renderer ignores the padding through `num_points`), the
clouds on the training device or on the host (rvt2cli.train.clouds), the rest on the device or, for what
the host computes a batch's targets from, in numpy arrays.
"""

from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch

from rvt2cli import runtime
from rvt2cli.model.observation import copy_points_into, points_kept
from rvt2cli.render.workspace import Workspace
from rvt2cli.tasks import TCP_AIM
from rvt2cli.train.samples import SampleSet


@dataclass
class PackedSamples:
    xyz: torch.Tensor          # [S, N, 3] float32, world frame; on the device, or on the host (`clouds_on_host`)
    rgb: torch.Tensor          # [S, N, 3] uint8, beside xyz
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
    clouds_on_host: bool = False  # xyz and rgb stay on the host, each batch's rows are moved (rvt2cli.train.clouds)
    shard: tuple[int, int] | None = None  # (rank, world): the host holds samples rank, rank + world, ... (cloud_shards)

    def __len__(self) -> int:
        return len(self.count)

    @property
    def device(self) -> torch.device:
        """Where batches are made (and every tensor but the host-resident clouds lives)."""
        return self.count.device

    def cloud_rows(self, idx: np.ndarray) -> np.ndarray:
        """Where samples `idx` are in xyz and rgb (a shard holds every world-th sample)."""
        if self.shard is None:
            return np.asarray(idx, np.int64)
        rank, world = self.shard
        if (np.asarray(idx) % world != rank).any():
            raise ValueError(f"samples outside shard {rank} of {world}: draw batches through cloud_shards.ShardedRows")
        return np.asarray(idx, np.int64) // world


def fit_clouds(samples: SampleSet, indices: list[int], max_points: int, rng: np.random.Generator,
               threads: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples `indices`' clouds as rows of `max_points` points (as `fit_points` fits one): xyz, rgb and
    each row's real points. The subsets are drawn from `rng` here, in row order, a chunk of rows at a time,
    and the chunks' copies run in `threads` (default: the usable cores), so the rows are the same however
    many threads copy them; the copies and the first touch of each row's memory are most of the time, and
    numpy copies without holding the GIL. A few chunks a thread are in flight, their subsets' indices with them."""
    n = len(indices)
    xyz = np.zeros((n, max_points, 3), np.float32)  # zero pages until written: each row's padding costs nothing
    rgb = np.zeros((n, max_points, 3), np.uint8)
    count = np.zeros(n, np.int64)

    def fill(rows: range, keeps: list) -> None:
        for row, keep in zip(rows, keeps):
            i = indices[row]
            count[row] = copy_points_into(xyz[row], rgb[row], samples.xyz[i], samples.rgb[i], keep)

    threads = max(1, threads or runtime.usable_cores())
    chunk = max(1, min(256, -(-n // (threads * 8))))  # rows differ in size: several chunks a thread
    in_flight = deque()
    with ThreadPoolExecutor(threads) as pool:
        for start in range(0, n, chunk):
            rows = range(start, min(n, start + chunk))
            in_flight.append(pool.submit(fill, rows, [points_kept(len(samples.xyz[indices[r]]), max_points, rng) for r in rows]))
            if len(in_flight) > 2 * threads:
                in_flight.popleft().result()
        for done in in_flight:
            done.result()
    return xyz, rgb, count


def pack(samples: SampleSet, indices: list[int], lang: torch.Tensor, max_points: int, device, seed: int = 0,
         aim_offsets: dict[str, list[float]] | None = None,
         phrasings: tuple[np.ndarray, np.ndarray] | None = None, clouds_on_host: bool = False) -> PackedSamples:
    """`aim_offsets`: task -> aim offset (m, TCP frame) of a policy trained with them (tasks left out: none).
    `phrasings`: each instruction's phrasings and their count (`samples.phrasing_table`), drawn from in
    training batches. `clouds_on_host`: the clouds stay on the host (`clouds.clouds_on_host` decides)."""
    xyz, rgb, count = fit_clouds(samples, indices, max_points, np.random.default_rng(seed))
    workspaces = [Workspace.from_bounds(samples.bounds[t]) for t in samples.tasks]
    pick = np.asarray(indices, dtype=np.int64)
    keyframe_index = np.asarray(samples.keyframe_index if samples.keyframe_index else [-1] * len(samples), np.int64)
    final_keyframe = np.asarray(samples.final_keyframe if samples.final_keyframe else [False] * len(samples), bool)
    keyframe_start = np.asarray(samples.keyframe_start if samples.keyframe_start else [False] * len(samples), bool)
    clouds = "cpu" if clouds_on_host else device
    return PackedSamples(
        xyz=torch.from_numpy(xyz).to(clouds), rgb=torch.from_numpy(rgb).to(clouds), count=torch.from_numpy(count).to(device),
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
        clouds_on_host=clouds_on_host,
    )
