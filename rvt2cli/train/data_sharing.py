"""The training data in every process of a several-GPU run: the first process reads and packs the samples
(`rvt2cli.train.training_data.read_data`) and sends them to the others, whole, or with the clouds of the
training samples in shards where they live on the host (`rvt2cli.train.cloud_shards`).
"""

from dataclasses import fields as dataclass_fields
from dataclasses import replace

import torch

from rvt2cli.errors import UserError
from rvt2cli.model.config import ModelConfig
from rvt2cli.train.checkpoint import Checkpoint
from rvt2cli.train.cloud_shards import SLICE_BYTES, send_shard, shard_length
from rvt2cli.train.options import TrainOptions
from rvt2cli.train.training_data import TrainingData, read_data


def load_data(opts: TrainOptions, cfg: ModelConfig, device, progress: bool, resume: Checkpoint | None, say) -> TrainingData:
    """The samples to train on, packed on `device` (their clouds there or on the host). In a several-GPU run
    the first process reads and packs them and sends them to the others, whose copy is the same as reading
    them would give (packing is seeded), but for host-resident clouds, of which each holds its shard: four
    processes reading 1,800 rvt2-18 episodes each took 4.5 of a 4 x H200 run's 15 minutes."""
    if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return read_data(opts, cfg, device, progress, resume, say)
    data, error = None, None
    if torch.distributed.get_rank() == 0:
        try:
            data = read_data(opts, cfg, device, progress, resume, say)
        except UserError as e:  # the others would otherwise wait for data that never comes
            error = str(e)
    return share_data(data, error, device)


def pickled_part(data: TrainingData) -> TrainingData:
    """What `share_data` pickles: `data` (its sample set without clouds), its packed samples without their
    tensors but with each tensor's shape, dtype and whether it lives on the host (the tensors travel apart)."""
    def outline(packed):
        if packed is None:
            return None
        tensors = {f.name: getattr(packed, f.name) for f in dataclass_fields(packed) if torch.is_tensor(getattr(packed, f.name))}
        return replace(packed, **dict.fromkeys(tensors)), {name: (t.shape, t.dtype, t.device.type == "cpu")
                                                           for name, t in tensors.items()}

    return replace(data, samples=replace(data.samples, xyz=[], rgb=[]), packed=outline(data.packed),
                   packed_val=outline(data.packed_val))


def share_data(data: TrainingData | None, error: str | None, device) -> TrainingData:
    """Process 0's `data` (or its error) in every process: the small parts pickled, the packed tensors sent
    as they are (NCCL between GPUs; host-resident ones a slice at a time through the GPU), except the
    training samples' host-resident clouds, of which each process gets its shard."""
    dist = torch.distributed
    rank, world = dist.get_rank(), dist.get_world_size()
    header = [None]
    if rank == 0:
        header = [("error", error)] if error is not None else [("data", pickled_part(data))]
    dist.broadcast_object_list(header, src=0, device=device if device.type == "cuda" else None)
    kind, payload = header[0]
    if kind == "error":
        raise UserError(payload)

    sharded = payload.packed[0].clouds_on_host   # the training clouds: a shard each

    def allocate(outlined, shard: bool = False):
        packed, shapes = outlined
        return replace(packed, **{name: torch.empty(shape if not (shard and name in CLOUDS) else
                                                    (shard_length(shape[0], rank, world), *shape[1:]),
                                                    dtype=dtype, device="cpu" if on_host else device)
                                  for name, (shape, dtype, on_host) in shapes.items()})

    received = data if rank == 0 else replace(payload, packed=allocate(payload.packed, sharded),
                                              packed_val=payload.packed_val and allocate(payload.packed_val))
    for packed, outlined, shard in ((received.packed, payload.packed, sharded), (received.packed_val, payload.packed_val, False)):
        for name in outlined[1] if outlined is not None else ():
            if not (shard and name in CLOUDS):
                broadcast(getattr(packed, name), device)
    if sharded:
        packed = received.packed
        shards = {name: send_shard(getattr(packed, name) if rank == 0 else None, None if rank == 0 else getattr(packed, name),
                                   rank, world, device) for name in CLOUDS}
        received = replace(received, packed=replace(packed, **shards, shard=(rank, world)))
    return received


CLOUDS = ("xyz", "rgb")   # what a shard holds part of


def broadcast(tensor: torch.Tensor, device: torch.device) -> None:
    """Process 0's `tensor` into every process's. NCCL sends only GPU memory: a host tensor travels through
    one GPU buffer a slice at a time."""
    dist = torch.distributed
    if tensor.device.type != "cpu" or device.type != "cuda" or dist.get_backend() != "nccl":
        dist.broadcast(tensor, src=0)
        return
    rows = max(1, SLICE_BYTES // max(1, tensor[:1].nbytes))
    for start in range(0, len(tensor), rows):
        part = tensor[start:start + rows]
        buffer = part.to(device) if dist.get_rank() == 0 else torch.empty_like(part, device=device)
        dist.broadcast(buffer, src=0)
        if dist.get_rank() != 0:
            part.copy_(buffer)
        torch.cuda.synchronize(device)   # one slice on the GPU at a time

