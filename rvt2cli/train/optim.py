"""The paper's optimiser and schedule: LAMB (8-bit from bitsandbytes on CUDA when it is installed),
linear warmup, then cosine decay to zero."""

import math

import torch
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR


class Lamb(Optimizer):
    """LAMB (You et al., 2020): Adam's update, rescaled per parameter tensor by the trust ratio
    ||w|| / ||update||, with decoupled weight decay inside the update."""

    def __init__(self, params, lr: float = 1e-3, betas=(0.9, 0.999), eps: float = 1e-6, weight_decay: float = 0.0):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps, weight_decay=weight_decay))

    @torch.no_grad()
    def step(self, closure=None):
        loss = closure() if closure is not None else None
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
                state["step"] += 1
                m, v = state["exp_avg"], state["exp_avg_sq"]
                m.mul_(beta1).add_(p.grad, alpha=1 - beta1)
                v.mul_(beta2).addcmul_(p.grad, p.grad, value=1 - beta2)
                m_hat = m / (1 - beta1 ** state["step"])
                v_hat = v / (1 - beta2 ** state["step"])
                update = m_hat / (v_hat.sqrt() + group["eps"])
                if group["weight_decay"]:
                    update.add_(p, alpha=group["weight_decay"])
                w_norm, u_norm = p.norm(), update.norm()
                trust = torch.where((w_norm > 0) & (u_norm > 0), w_norm / u_norm, torch.ones_like(w_norm))
                p.sub_(update * (group["lr"] * trust))
        return loss


def make_optimizer(params, lr: float, weight_decay: float, device: torch.device, eight_bit: bool = True) -> tuple[Optimizer, str]:
    """8-bit LAMB (bitsandbytes) on CUDA when available, else our LAMB. Returns (optimizer, its name)."""
    if eight_bit and device.type == "cuda":
        try:
            import bitsandbytes as bnb

            return bnb.optim.LAMB8bit(params, lr=lr, weight_decay=weight_decay), "LAMB8bit (bitsandbytes)"
        except (ImportError, RuntimeError, AttributeError):
            pass
    return Lamb(params, lr=lr, weight_decay=weight_decay), "LAMB"


def warmup_cosine(optimizer: Optimizer, warmup_steps: int, total_steps: int) -> LambdaLR:
    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        progress = (step - warmup_steps) / max(1, total_steps - warmup_steps)
        return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))

    return LambdaLR(optimizer, factor)
