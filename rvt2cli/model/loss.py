"""Losses of DESIGN.md section 2: per-view heatmap cross-entropy against Gaussian targets (every
stage), cross-entropy for the three rotation bins (against the true bin, or a Gaussian around the true
angle: `rotation.soft_bin_targets`), the gripper and the collision flag."""

import torch
import torch.nn.functional as F

from rvt2cli.model.locate import gaussian_targets
from rvt2cli.model.rotation import soft_bin_targets


def heatmap_cross_entropy(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """logits, target [B, V, H, W] (target sums to 1 per view) -> mean over batch and views."""
    log_probs = F.log_softmax(logits.float().flatten(-2), dim=-1)
    return -(target.flatten(-2) * log_probs).sum(-1).mean()


def policy_loss(outputs: dict, target_position: torch.Tensor, target_rot_bins: torch.Tensor,
                target_gripper: torch.Tensor, target_collision: torch.Tensor, image_size: int, sigma: float,
                target_euler_deg: torch.Tensor | None = None, rotation_sigma_deg: float = 0.0) -> dict:
    """With `rotation_sigma_deg` > 0 the rotation targets are Gaussians around `target_euler_deg` [B, 3]."""
    terms = {}
    for i, stage in enumerate(outputs["stages"]):
        target = gaussian_targets(target_position, stage.cameras, image_size, sigma)
        terms[f"heatmap{i + 1}"] = heatmap_cross_entropy(stage.logits, target)
    action = outputs["action"]
    soft = None
    if rotation_sigma_deg > 0:
        soft = soft_bin_targets(target_euler_deg, action["rot_x"].shape[-1], rotation_sigma_deg)
    for axis, key in enumerate(("rot_x", "rot_y", "rot_z")):
        target = target_rot_bins[:, axis] if soft is None else soft[:, axis]
        terms[key] = F.cross_entropy(action[key].float(), target)
    terms["gripper"] = F.cross_entropy(action["gripper"].float(), target_gripper)
    terms["collision"] = F.cross_entropy(action["collision"].float(), target_collision)
    terms["total"] = sum(terms.values())
    return terms
