"""One training step: render both stages, forward, every head and loss, backward, gradient clipping,
the optimiser and the schedule. `rvt2 train` runs it; `benchmarks/policy_bench.py` times it.

A batch given as `MicroBatches` (`rvt2 train --micro-batch`) is run a part at a time, each part's loss
weighted by its share of the rows before its backward pass, so that the gradients add up to the whole
batch's (every loss term is a mean over the batch) while only one part's activations are held; under DDP
the gradients are averaged across processes once, in the last part's backward pass. Clipping, the
non-finite guard, the optimiser and the schedule then see one step, as without parts.

Nothing in a step waits for the GPU: whether the loss and the gradient were finite is decided on the
device and handed to the optimiser (`skip`), and the step returns device tensors that the loop reads
back only every few steps.
"""

from contextlib import nullcontext
from dataclasses import dataclass

import torch

from rvt2cli.model.loss import policy_loss
from rvt2cli.train.batches import Batch, MicroBatches


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

    def __call__(self, batch: Batch | MicroBatches) -> StepResult:
        parts = [batch] if isinstance(batch, Batch) else batch
        self.optimizer.zero_grad(set_to_none=True)
        losses: dict[str, torch.Tensor] = {}
        for i, part in enumerate(parts):
            with self.gradients_averaged(i == len(parts) - 1):
                part_losses = self.losses(part)
                if len(parts) > 1:  # the part's share of the whole batch's mean
                    part_losses = {name: value * parts.weight(i) for name, value in part_losses.items()}
                part_losses["total"].backward()
            for name, value in part_losses.items():
                losses[name] = value.detach() if name not in losses else losses[name] + value.detach()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.policy.parameters(), self.clip)
        finite = torch.isfinite(losses["total"]) & torch.isfinite(grad_norm)
        self.optimizer.step(skip=~finite)
        self.schedule.step()
        return StepResult(losses, grad_norm.detach(), finite)

    def gradients_averaged(self, now: bool):
        """Under DDP, whether this backward pass averages the gradients across processes (the last part's)."""
        return nullcontext() if now or not hasattr(self.model, "no_sync") else self.model.no_sync()

    def losses(self, batch: Batch) -> dict[str, torch.Tensor]:
        """The forward pass and every loss term of one batch (or part)."""
        with torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=self.amp):
            outputs = self.model(batch.obs, batch.position, batch.rot_bins, batch.stage2_center)
        return policy_loss(outputs, batch.position, batch.rot_bins, batch.gripper, batch.collision,
                           self.cfg.image_size, self.cfg.heatmap_sigma, batch.euler_deg, self.cfg.rotation_sigma_deg)
