"""Pre-norm transformer blocks: multi-head attention through PyTorch's fused
`scaled_dot_product_attention` (flash / memory-efficient kernels on GPU) and a GEGLU feed-forward."""

import torch
import torch.nn.functional as F
from torch import nn


class Attention(nn.Module):
    def __init__(self, width: int, heads: int, head_dim: int, dropout: float = 0.0):
        super().__init__()
        self.heads, self.head_dim, self.dropout = heads, head_dim, dropout
        self.to_qkv = nn.Linear(width, 3 * heads * head_dim, bias=False)
        self.to_out = nn.Linear(heads * head_dim, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, _ = x.shape
        q, k, v = self.to_qkv(x).view(b, n, 3, self.heads, self.head_dim).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v, dropout_p=self.dropout if self.training else 0.0)
        return self.to_out(out.transpose(1, 2).reshape(b, n, self.heads * self.head_dim))


class GEGLU(nn.Module):
    """Gated feed-forward: (x W1) * gelu(x W2), then a projection back (Shazeer, 2020)."""

    def __init__(self, width: int, ratio: int):
        super().__init__()
        self.proj_in = nn.Linear(width, 2 * ratio * width)
        self.proj_out = nn.Linear(ratio * width, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # Two products over the halves of proj_in rather than one product chunked in two: the chunk's
        # backward is one pointwise kernel writing both halves of the gradient, which ran 4x slower than
        # the forward's on an H200 (docs/BENCHMARKS.md, "Training step profile"). Same weights, same result.
        hidden = self.proj_out.in_features
        weight, bias = self.proj_in.weight, self.proj_in.bias
        value = F.linear(x, weight[:hidden], bias[:hidden])
        gate = F.linear(x, weight[hidden:], bias[hidden:])
        return self.proj_out(value * F.gelu(gate))


class Block(nn.Module):
    def __init__(self, width: int, heads: int, head_dim: int, mlp_ratio: int, dropout: float = 0.0):
        super().__init__()
        self.norm_attn = nn.LayerNorm(width)
        self.attn = Attention(width, heads, head_dim, dropout)
        self.norm_ff = nn.LayerNorm(width)
        self.ff = GEGLU(width, mlp_ratio)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm_attn(x))
        return x + self.ff(self.norm_ff(x))
