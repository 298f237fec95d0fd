"""One copy of the training data for every process of a several-GPU run: the first process reads and
packs the samples (`rvt2cli.train.training_data.read_data`) and sends them to the others.
"""

from dataclasses import fields as dataclass_fields
from dataclasses import replace

import torch

from rvt2cli.errors import UserError
from rvt2cli.model.config import ModelConfig
from rvt2cli.train.checkpoint import Checkpoint
from rvt2cli.train.options import TrainOptions
from rvt2cli.train.training_data import TrainingData, read_data


def load_data(opts: TrainOptions, cfg: ModelConfig, device, progress: bool, resume: Checkpoint | None, say) -> TrainingData:
    """The samples to train on, packed on `device`. In a several-GPU run the first process reads and packs
    them and sends them to the others, whose copy is the same as reading them would give (packing is
    seeded): four processes reading 1,800 rvt2-18 episodes each took 4.5 of a 4 x H200 run's 15 minutes."""
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
    """What `share_data` pickles: `data` without the sample set's clouds, its packed samples without their
    tensors but with each tensor's shape and dtype (the tensors travel apart)."""
    def outline(packed):
        if packed is None:
            return None
        tensors = {f.name: getattr(packed, f.name) for f in dataclass_fields(packed) if torch.is_tensor(getattr(packed, f.name))}
        return replace(packed, **dict.fromkeys(tensors)), {name: (t.shape, t.dtype) for name, t in tensors.items()}

    return replace(data, samples=replace(data.samples, xyz=[], rgb=[]), packed=outline(data.packed),
                   packed_val=outline(data.packed_val))


def share_data(data: TrainingData | None, error: str | None, device) -> TrainingData:
    """Process 0's `data` (or its error) in every process: the small parts pickled, the packed tensors sent
    as they are (NCCL between GPUs). Process 0's sample set keeps its clouds, the others' copy has none
    (only the packed ones are trained on)."""
    dist = torch.distributed
    rank = dist.get_rank()
    header = [None]
    if rank == 0:
        header = [("error", error)] if error is not None else [("data", pickled_part(data))]
    dist.broadcast_object_list(header, src=0, device=device if device.type == "cuda" else None)
    kind, payload = header[0]
    if kind == "error":
        raise UserError(payload)

    def allocate(outlined):
        packed, shapes = outlined
        return replace(packed, **{name: torch.empty(shape, dtype=dtype, device=device) for name, (shape, dtype) in shapes.items()})

    received = data if rank == 0 else replace(payload, packed=allocate(payload.packed),
                                              packed_val=payload.packed_val and allocate(payload.packed_val))
    for packed, outlined in ((received.packed, payload.packed), (received.packed_val, payload.packed_val)):
        for name in outlined[1] if outlined is not None else ():
            dist.broadcast(getattr(packed, name), src=0)
    return received


