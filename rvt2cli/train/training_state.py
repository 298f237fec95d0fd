"""Everything besides the weights that a resumed run needs to continue exactly (`TrainingState`), and
the processes of a several-GPU run (torchrun's environment) that it is kept for.
"""

import datetime
import os
from dataclasses import dataclass
from pathlib import Path

import torch

from rvt2cli.errors import UserError


DISTRIBUTED_TIMEOUT = datetime.timedelta(hours=1)


def init_distributed() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not torch.distributed.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        # the other processes wait in a collective while the first reads the episodes (`load_data`), which can
        # take longer than torch's 10-minute default on a large dataset
        torch.distributed.init_process_group(backend, timeout=DISTRIBUTED_TIMEOUT)
    return (torch.distributed.get_rank() if world > 1 else 0), world


def gather(value, world: int) -> list:
    """Every rank's `value` (a CPU tensor or a number), in rank order."""
    if world == 1:
        return [value]
    values = [None] * world
    torch.distributed.all_gather_object(values, value)
    return values


@dataclass
class TrainingState:
    """Everything besides the weights that a resumed run needs to continue exactly. A new piece of
    state is added here, in `save` and `restore`, and nowhere else."""

    optimizer: torch.optim.Optimizer
    schedule: torch.optim.lr_scheduler.LRScheduler
    generator: torch.Generator      # this rank's sampling and augmentation
    step: int = 0
    skipped: int = 0

    def save(self, world: int, sampling_state: torch.Tensor | None = None) -> dict:
        """The state of every rank (call on every rank; the result is complete on all of them).
        `sampling_state`: the generator's state to keep, if not its state now (the loop draws a batch ahead)."""
        sampling_state = self.generator.get_state() if sampling_state is None else sampling_state
        return {"optimizer": self.optimizer.state_dict(), "schedule": self.schedule.state_dict(),
                "generators": gather(sampling_state, world), "torch_rng": gather(torch.get_rng_state(), world),
                "step": self.step, "skipped": self.skipped, "world_size": world}

    def restore(self, state: dict, rank: int, world: int, where: Path) -> None:
        saved_world = state.get("world_size", len(state["generators"]))
        if saved_world != world:
            raise UserError(f"{where}: the run was trained by {saved_world} process(es), this resume has {world}; "
                            f"resume with the same number (torchrun --nproc-per-node {saved_world})")
        self.optimizer.load_state_dict(state["optimizer"])
        self.schedule.load_state_dict(state["schedule"])
        self.generator.set_state(state["generators"][rank])
        torch.set_rng_state(state["torch_rng"][rank])
        self.step, self.skipped = int(state["step"]), int(state["skipped"])

