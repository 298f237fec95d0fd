"""Per-view heatmaps from token features.

RVT-2 uses convex upsampling (RAFT, Teed & Deng 2020): at token resolution, predict a coarse logit
per token and, for each of the p x p pixels a token covers, softmax weights over its 3 x 3 token
neighbourhood; each pixel's logit is that convex combination of coarse logits. No full-resolution
feature map is ever built, which is where the memory saving comes from. (The neighbourhood is
gathered with padding and slices, what F.unfold does, in a form that exports to ONNX.) RVT-1's alternative (the
ablation baseline) upsamples the features themselves with a transposed convolution.
"""

import torch
import torch.nn.functional as F
from torch import nn


class ConvexUpsampleHeatmap(nn.Module):
    def __init__(self, width: int, patch: int, hidden: int):
        super().__init__()
        self.patch = patch
        self.coarse = nn.Sequential(nn.Conv2d(width, hidden, 3, padding=1), nn.GELU(), nn.Conv2d(hidden, 1, 1))
        self.mask = nn.Sequential(nn.Conv2d(width, hidden, 3, padding=1), nn.GELU(), nn.Conv2d(hidden, 9 * patch * patch, 1))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """features [N, D, t, t] -> heatmap logits [N, t*p, t*p]."""
        n, _, t, _ = features.shape
        p = self.patch
        coarse = self.coarse(features)                                   # [N, 1, t, t]
        weights = self.mask(features).view(n, 9, p, p, t, t).softmax(dim=1)
        padded = F.pad(coarse, (1, 1, 1, 1))
        neighbours = torch.stack([padded[:, 0, dy:dy + t, dx:dx + t] for dy in range(3) for dx in range(3)], dim=1)
        neighbours = neighbours.view(n, 9, 1, 1, t, t)                   # the 3 x 3 token neighbourhood, row-major
        fine = (weights * neighbours).sum(dim=1)                         # [N, p, p, t, t]
        return fine.permute(0, 3, 1, 4, 2).reshape(n, t * p, t * p)

    def convex_weights(self, features: torch.Tensor) -> torch.Tensor:
        """The per-pixel combination weights [N, 9, p, p, t, t] (each sums to 1 over the 9 neighbours)."""
        n, _, t, _ = features.shape
        return self.mask(features).view(n, 9, self.patch, self.patch, t, t).softmax(dim=1)


class TransposedConvHeatmap(nn.Module):
    """RVT-1: upsample features to full resolution, then predict one logit per pixel."""

    def __init__(self, width: int, patch: int, hidden: int):
        super().__init__()
        self.up = nn.Sequential(nn.ConvTranspose2d(width, hidden, kernel_size=patch, stride=patch), nn.GELU())
        self.out = nn.Conv2d(hidden, 1, 3, padding=1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.out(self.up(features))[:, 0]


def make_heatmap_head(width: int, patch: int, hidden: int, convex: bool) -> nn.Module:
    return (ConvexUpsampleHeatmap if convex else TransposedConvHeatmap)(width, patch, hidden)
