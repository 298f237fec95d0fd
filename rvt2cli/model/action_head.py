"""Rotation, gripper and collision heads.

RVT-2's location-conditioned rotation: from every view's stage-2 token features, take the feature at
the end-effector location (bilinearly sampled at its projection: the ground truth while training, the
prediction at inference) and the view's max-pooled feature; an MLP over all views' features predicts
the Euler bins autoregressively: x, then y given x, then z given x and y, plus gripper open and
"ignore collisions" (2-way each). RVT-1's global variant (the ablation) replaces the sampled feature
with a heatmap-weighted mean of the view's features. With `coarse_action_features` the MLP also gets
stage 1's features at the same point, read the same way through their own projection.
"""

import torch
import torch.nn.functional as F
from torch import nn

from rvt2cli.model.config import ModelConfig


class ActionHead(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        d = cfg.rotation_feature_dim
        self.reduce = nn.Conv2d(cfg.width, d, 1)
        self.reduce_coarse = nn.Conv2d(cfg.width, d, 1) if self.reads_coarse else None
        views = len(cfg.views)
        bins = cfg.rotation_bins
        stages_read = 2 if self.reads_coarse else 1
        self.trunk = nn.Sequential(nn.Linear(stages_read * views * 2 * d, cfg.head_hidden), nn.GELU(),
                                   nn.Linear(cfg.head_hidden, cfg.head_hidden), nn.GELU())
        self.rot_x = nn.Linear(cfg.head_hidden, bins)
        self.rot_y = nn.Linear(cfg.head_hidden + bins, bins)
        self.rot_z = nn.Linear(cfg.head_hidden + 2 * bins, bins)
        self.gripper = nn.Linear(cfg.head_hidden, 2)
        self.collision = nn.Linear(cfg.head_hidden, 2)

    @property
    def reads_coarse(self) -> bool:
        return self.cfg.coarse_action_features and self.cfg.stages == 2

    def features(self, tokens: torch.Tensor, uv: torch.Tensor | None, heatmap_probs: torch.Tensor | None,
                 coarse: bool = False) -> torch.Tensor:
        """tokens [B, V, D, t, t] of stage 2 (or of stage 1, `coarse`); uv [B, V, 2] pixel coords of the
        location (local features) or heatmap_probs [B, V, H, W] (global features) -> [B, V * 2 * d]."""
        b, v = tokens.shape[:2]
        f = (self.reduce_coarse if coarse else self.reduce)(tokens.flatten(0, 1))   # [B*V, d, t, t]
        pooled = f.amax(dim=(-2, -1))                                    # [B*V, d]
        if self.cfg.local_rotation_features:
            size = self.cfg.image_size
            grid = (uv.flatten(0, 1) * (2.0 / size) - 1.0)[:, None, None, :]   # [B*V, 1, 1, 2] in [-1, 1]
            second = F.grid_sample(f, grid.to(f.dtype), mode="bilinear", align_corners=False)[:, :, 0, 0]
        else:
            weights = F.adaptive_avg_pool2d(heatmap_probs.flatten(0, 1)[:, None], f.shape[-1])  # [B*V, 1, t, t]
            weights = weights / weights.sum(dim=(-2, -1), keepdim=True).clamp_min(1e-12)
            second = (f * weights).sum(dim=(-2, -1))
        return torch.cat([pooled, second], dim=-1).view(b, -1)

    def forward(self, features: torch.Tensor, rot_bins: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """With `rot_bins` [B, 3] (training) the y and z heads see the true x (and y) bins; without,
        they see the predicted ones (inference)."""
        h = self.trunk(features)
        bins = self.cfg.rotation_bins
        x = self.rot_x(h)
        x_bin = rot_bins[:, 0] if rot_bins is not None else x.argmax(-1)
        x_onehot = F.one_hot(x_bin, bins).to(h.dtype)
        y = self.rot_y(torch.cat([h, x_onehot], dim=-1))
        y_bin = rot_bins[:, 1] if rot_bins is not None else y.argmax(-1)
        z = self.rot_z(torch.cat([h, x_onehot, F.one_hot(y_bin, bins).to(h.dtype)], dim=-1))
        return {"rot_x": x, "rot_y": y, "rot_z": z, "gripper": self.gripper(h), "collision": self.collision(h)}
