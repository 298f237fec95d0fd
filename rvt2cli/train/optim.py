"""The paper's optimiser and schedule: LAMB (`rvt2cli.train.lamb`; with 8-bit states,
`rvt2cli.train.lamb8bit`, on CUDA), linear warmup, then cosine decay to zero."""

import math

import torch
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR

from rvt2cli.train.lamb import Lamb
from rvt2cli.train.lamb8bit import Lamb8bit


def make_optimizer(params, lr: float, weight_decay: float, device: torch.device, eight_bit: bool = True) -> tuple[Optimizer, str]:
    """LAMB with 8-bit states on CUDA (the paper's; ours, `rvt2cli.train.lamb8bit`), else with
    32-bit states. Returns (optimizer, description)."""
    if eight_bit and device.type == "cuda":
        return Lamb8bit(params, lr=lr, weight_decay=weight_decay), "LAMB, 8-bit blockwise states"
    return Lamb(params, lr=lr, weight_decay=weight_decay), "LAMB"


def warmup_cosine(optimizer: Optimizer, warmup_steps: int, total_steps: int) -> LambdaLR:
    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        progress = (step - warmup_steps) / max(1, total_steps - warmup_steps)
        return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))

    return LambdaLR(optimizer, factor)
