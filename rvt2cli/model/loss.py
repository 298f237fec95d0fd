"""Losses of DESIGN.md section 2: per-view heatmap cross-entropy against Gaussian targets (every
stage), cross-entropy for the three rotation bins, the gripper and the collision flag."""

import torch
import torch.nn.functional as F

from rvt2cli.model.locate import gaussian_targets


def heatmap_cross_entropy(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """logits, target [B, V, H, W] (target sums to 1 per view) -> mean over batch and views."""
    log_probs = F.log_softmax(logits.float().flatten(-2), dim=-1)
    return -(target.flatten(-2) * log_probs).sum(-1).mean()


def policy_loss(outputs: dict, target_position: torch.Tensor, target_rot_bins: torch.Tensor,
                target_gripper: torch.Tensor, target_collision: torch.Tensor, image_size: int, sigma: float) -> dict:
    terms = {}
    for i, stage in enumerate(outputs["stages"]):
        target = gaussian_targets(target_position, stage.cameras, image_size, sigma)
        terms[f"heatmap{i + 1}"] = heatmap_cross_entropy(stage.logits, target)
    action = outputs["action"]
    for axis, key in enumerate(("rot_x", "rot_y", "rot_z")):
        terms[key] = F.cross_entropy(action[key].float(), target_rot_bins[:, axis])
    terms["gripper"] = F.cross_entropy(action["gripper"].float(), target_gripper)
    terms["collision"] = F.cross_entropy(action["collision"].float(), target_collision)
    terms["total"] = sum(terms.values())
    return terms
