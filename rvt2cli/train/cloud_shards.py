"""Host-resident clouds under DDP: each process holds a shard, and a batch's rows come from where they are.

With the clouds on the host (`--samples-on host`), a several-GPU run keeps one copy of them in all: process
r of W holds samples r, r + W, r + 2W, ... (every task in every shard, so each serves about as many rows
as it asks for), not W copies (four processes of rvt2-18 on one host: 43.7 GiB instead of 175; four times
the demos across two hosts: each holds its processes' shards). The first process still reads and packs
all samples and sends each process its shard (`send_shard`).

Every process draws its batches as before, from its own generator over all samples, so the global
batches are the ones a run with a full copy per process trains on. A batch's rows are then exchanged:
the processes tell each other the samples they drew (a few hundred indices, over a host-side gloo group:
no GPU synchronisation), each gathers the rows of its shard that any process asked for and copies them
to its GPU (`clouds.StagedRows`), and one all-to-all (NCCL, over NVLink within a host) hands every
process its rows, which are put back in the drawn order.
"""

import numpy as np
import torch
import torch.distributed as dist

from rvt2cli.train.clouds import StagedRows

SLICE_BYTES = 1 << 30   # host-resident tensors cross a GPU to another process this much at a time


def shard_length(samples: int, rank: int, world: int) -> int:
    """How many of `samples` the shard of process `rank` of `world` holds (samples rank, rank + world, ...)."""
    return len(range(rank, samples, world))


def send_shard(full: torch.Tensor | None, shard: torch.Tensor | None, rank: int, world: int, device: torch.device
               ) -> torch.Tensor:
    """Process 0's `full` tensor, every process's shard of it: process 0 passes `full` (and None) and keeps
    its own shard, the others pass an empty `shard` to fill. Over NCCL a slice at a time through the GPU."""
    through_gpu = device.type == "cuda" and dist.get_backend() == "nccl"
    if rank == 0:
        for q in range(1, world):
            part = full[q::world]
            rows = max(1, SLICE_BYTES // max(1, part[:1].nbytes))
            for start in range(0, len(part), rows):
                piece = part[start:start + rows]
                dist.send(piece.to(device) if through_gpu else piece.contiguous(), dst=q)
                if through_gpu:  # one slice on the GPU at a time, however far the host could run ahead
                    torch.cuda.synchronize(device)
        return full[0::world].clone()
    rows = max(1, SLICE_BYTES // max(1, shard[:1].nbytes))
    for start in range(0, len(shard), rows):
        target = shard[start:start + rows]
        piece = torch.empty_like(target, device=device) if through_gpu else target
        dist.recv(piece, src=0)
        if through_gpu:
            target.copy_(piece)
    return shard


class ShardedRows:
    """A batch's clouds for this process, from the shards of all (see the module's docstring). Every process
    calls it once per batch (or part), in the same order, as `BatchStream` does."""

    def __init__(self, xyz: torch.Tensor, rgb: torch.Tensor, rank: int, world: int, device: torch.device, rows: int):
        self.rank, self.world, self.device = rank, world, device
        self.staged = StagedRows(xyz, rgb, device, rows)
        # the drawn indices travel between hosts' memories, never through a GPU (NCCL would make the host wait for it)
        self.indices_group = dist.new_group(backend="gloo") if dist.get_backend() == "nccl" else None

    def __call__(self, idx: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        idx = np.asarray(idx, np.int64)
        drawn = [torch.empty(len(idx), dtype=torch.int64) for _ in range(self.world)]
        dist.all_gather(drawn, torch.from_numpy(idx), group=self.indices_group)
        # what this process sends: for each process in turn, the rows of this shard it drew, in its order
        asked = [d.numpy() for d in drawn]
        send = [a[a % self.world == self.rank] // self.world for a in asked]
        owner = idx % self.world
        receive = [int((owner == q).sum()) for q in range(self.world)]
        xyz_out, rgb_out = self.staged(np.concatenate(send))
        xyz = torch.empty((len(idx), *xyz_out.shape[1:]), dtype=xyz_out.dtype, device=self.device)
        rgb = torch.empty((len(idx), *rgb_out.shape[1:]), dtype=rgb_out.dtype, device=self.device)
        sent = [len(s) for s in send]
        dist.all_to_all_single(xyz, xyz_out, receive, sent)
        dist.all_to_all_single(rgb, rgb_out, receive, sent)
        # received from process 0 first, then 1, ...: back to the drawn order
        order = torch.from_numpy(np.concatenate([np.flatnonzero(owner == q) for q in range(self.world)]))
        order = order.pin_memory().to(self.device, non_blocking=True) if self.device.type == "cuda" else order
        return xyz.new_empty(xyz.shape).index_copy_(0, order, xyz), rgb.new_empty(rgb.shape).index_copy_(0, order, rgb)
