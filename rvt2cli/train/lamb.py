"""LAMB (You et al., 2020) with 32-bit states: the arithmetic of the paper's optimiser, which the 8-bit
LAMB (`rvt2cli.train.lamb8bit`) shares and which updates that one's small tensors.

`step(skip=...)` takes a boolean tensor on the parameters' device: where it is true (the step's loss or
gradient was not finite) the step changes nothing: not the weights, not the moments, not the step
count. The decision stays on the device, so the training loop needs no host synchronisation per step.
"""

import torch
from torch.optim import Optimizer


def step_weight(grads: list[torch.Tensor], skip: torch.Tensor | None, device) -> torch.Tensor:
    """The step's weight as a float tensor: 0 where `skip` is true, else 1. Non-finite gradient values
    are zeroed in place (their step is discarded; NaN would survive a multiplication by 0)."""
    if skip is None:
        return torch.ones((), dtype=torch.float32, device=device)
    for g in grads:
        torch.nan_to_num_(g, nan=0.0, posinf=0.0, neginf=0.0)
    return (~skip).to(torch.float32)


class Lamb(Optimizer):
    """LAMB (You et al., 2020): Adam's update, rescaled per parameter tensor by the trust ratio
    ||w|| / ||update||, with decoupled weight decay inside the update. Written with torch's
    multi-tensor (`_foreach`) ops: a handful of kernels per step for the whole model."""

    def __init__(self, params, lr: float = 1e-3, betas=(0.9, 0.999), eps: float = 1e-6, weight_decay: float = 0.0):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps, weight_decay=weight_decay))

    @torch.no_grad()
    def step(self, closure=None, skip: torch.Tensor | None = None):
        loss = closure() if closure is not None else None
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            beta1, beta2 = group["betas"]
            for p in params:
                state = self.state[p]
                if not state:
                    state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
            grads = [p.grad for p in params]
            m = [self.state[p]["exp_avg"] for p in params]
            v = [self.state[p]["exp_avg_sq"] for p in params]
            keep = step_weight(grads, skip, params[0].device)
            count = self.state[params[0]]["step"]
            count += keep
            for p in params[1:]:
                self.state[p]["step"].copy_(count)
            # moments: a skipped step (keep = 0) multiplies them by 1 and adds nothing
            decay1, decay2 = 1 - keep * (1 - beta1), 1 - keep * (1 - beta2)
            torch._foreach_mul_(m, decay1)
            torch._foreach_add_(m, torch._foreach_mul(grads, 1 - decay1))
            torch._foreach_mul_(v, decay2)
            torch._foreach_add_(v, torch._foreach_mul(torch._foreach_mul(grads, grads), 1 - decay2))
            # m_hat / (sqrt(v_hat) + eps), with m_hat = m / (1 - beta1^t), v_hat = v / (1 - beta2^t)
            t = count.clamp_min(1)
            denom = torch._foreach_sqrt(v)
            torch._foreach_div_(denom, torch.sqrt(1 - beta2**t))
            torch._foreach_add_(denom, group["eps"])
            update = torch._foreach_div(m, denom)
            torch._foreach_div_(update, 1 - beta1**t)
            if group["weight_decay"]:
                torch._foreach_add_(update, params, alpha=group["weight_decay"])
            w_norm = torch.stack(torch._foreach_norm(params))
            u_norm = torch.stack(torch._foreach_norm(update))
            trust = torch.where((w_norm > 0) & (u_norm > 0), w_norm / u_norm, torch.ones_like(w_norm))
            torch._foreach_mul_(update, list((trust * (-group["lr"] * keep)).unbind()))
            torch._foreach_add_(params, update)
        return loss
