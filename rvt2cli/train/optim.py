"""The paper's optimiser and schedule: LAMB (8-bit from bitsandbytes on CUDA when it is installed),
linear warmup, then cosine decay to zero."""

import math

import torch
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR


class Lamb(Optimizer):
    """LAMB (You et al., 2020): Adam's update, rescaled per parameter tensor by the trust ratio
    ||w|| / ||update||, with decoupled weight decay inside the update. Written with torch's
    multi-tensor (`_foreach`) ops: a handful of kernels per step for the whole model."""

    def __init__(self, params, lr: float = 1e-3, betas=(0.9, 0.999), eps: float = 1e-6, weight_decay: float = 0.0):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps, weight_decay=weight_decay))

    @torch.no_grad()
    def step(self, closure=None):
        loss = closure() if closure is not None else None
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            beta1, beta2 = group["betas"]
            for p in params:
                state = self.state[p]
                if not state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
                state["step"] += 1
            grads = [p.grad for p in params]
            m = [self.state[p]["exp_avg"] for p in params]
            v = [self.state[p]["exp_avg_sq"] for p in params]
            step = self.state[params[0]]["step"]
            torch._foreach_mul_(m, beta1)
            torch._foreach_add_(m, grads, alpha=1 - beta1)
            torch._foreach_mul_(v, beta2)
            torch._foreach_addcmul_(v, grads, grads, value=1 - beta2)
            # m_hat / (sqrt(v_hat) + eps), with m_hat = m / (1 - beta1^t), v_hat = v / (1 - beta2^t)
            denom = torch._foreach_sqrt(v)
            torch._foreach_div_(denom, math.sqrt(1 - beta2**step))
            torch._foreach_add_(denom, group["eps"])
            update = torch._foreach_div(m, denom)
            torch._foreach_div_(update, 1 - beta1**step)
            if group["weight_decay"]:
                torch._foreach_add_(update, params, alpha=group["weight_decay"])
            w_norm = torch.stack(torch._foreach_norm(params))
            u_norm = torch.stack(torch._foreach_norm(update))
            trust = torch.where((w_norm > 0) & (u_norm > 0), w_norm / u_norm, torch.ones_like(w_norm))
            torch._foreach_mul_(update, list((trust * -group["lr"]).unbind()))
            torch._foreach_add_(params, update)
        return loss


def _eight_bit_lamb_works(device: torch.device) -> str | None:
    """None if bitsandbytes' 8-bit LAMB runs here, else why not (recent releases dropped its kernel)."""
    try:
        import bitsandbytes as bnb

        probe = torch.nn.Parameter(torch.zeros(4096, device=device))
        probe.grad = torch.ones_like(probe)
        bnb.optim.LAMB8bit([probe], lr=1e-3).step()
        return None
    except Exception as e:  # noqa: BLE001 - any failure means: use the 32-bit LAMB
        return f"{type(e).__name__}: {e}".splitlines()[0][:160]


def make_optimizer(params, lr: float, weight_decay: float, device: torch.device, eight_bit: bool = True) -> tuple[Optimizer, str]:
    """8-bit LAMB (bitsandbytes) on CUDA when it works there, else our LAMB. Returns (optimizer, description)."""
    if eight_bit and device.type == "cuda":
        problem = _eight_bit_lamb_works(device)
        if problem is None:
            import bitsandbytes as bnb

            return bnb.optim.LAMB8bit(params, lr=lr, weight_decay=weight_decay), "LAMB8bit (bitsandbytes)"
        return Lamb(params, lr=lr, weight_decay=weight_decay), f"LAMB (32-bit; no 8-bit LAMB: {problem})"
    return Lamb(params, lr=lr, weight_decay=weight_decay), "LAMB"


def warmup_cosine(optimizer: Optimizer, warmup_steps: int, total_steps: int) -> LambdaLR:
    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        progress = (step - warmup_steps) / max(1, total_steps - warmup_steps)
        return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))

    return LambdaLR(optimizer, factor)
