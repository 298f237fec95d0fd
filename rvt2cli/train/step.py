"""One training step: render both stages, forward, every head and loss, backward, gradient clipping,
the optimiser and the schedule. `rvt2 train` runs it; `benchmarks/policy_bench.py` times it.

Nothing in a step waits for the GPU: whether the loss and the gradient were finite is decided on the
device and handed to the optimiser (`skip`), and the step returns device tensors that the loop reads
back only every few steps.
"""

from dataclasses import dataclass

import torch

from rvt2cli.model.loss import policy_loss
from rvt2cli.train.batches import Batch


@dataclass
class StepResult:
    losses: dict[str, torch.Tensor]   # every loss term and "total", 0-d tensors on the device
    grad_norm: torch.Tensor           # before clipping
    finite: torch.Tensor              # 0-d bool: the step was applied (False: skipped as non-finite)


class TrainStep:
    def __init__(self, policy, optimizer, schedule, amp: bool, clip: float, model=None):
        """`model` is what runs the forward pass: the policy itself or its DistributedDataParallel wrapper."""
        self.policy, self.model = policy, model if model is not None else policy
        self.optimizer, self.schedule = optimizer, schedule
        self.cfg = policy.cfg
        self.amp, self.clip = amp, clip

    def __call__(self, batch: Batch) -> StepResult:
        with torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=self.amp):
            outputs = self.model(batch.obs, batch.position, batch.rot_bins, batch.stage2_center)
        losses = policy_loss(outputs, batch.position, batch.rot_bins, batch.gripper, batch.collision,
                             self.cfg.image_size, self.cfg.heatmap_sigma, batch.euler_deg, self.cfg.rotation_sigma_deg)
        self.optimizer.zero_grad(set_to_none=True)
        losses["total"].backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.policy.parameters(), self.clip)
        finite = torch.isfinite(losses["total"].detach()) & torch.isfinite(grad_norm)
        self.optimizer.step(skip=~finite)
        self.schedule.step()
        return StepResult({k: v.detach() for k, v in losses.items()}, grad_norm.detach(), finite)
