"""The multi-view transformer (one per stage): rendered views + proprio + language -> token features.

Each view is cut into patches (a convolution with kernel = stride = patch size) of 10-channel pixels;
the proprio vector is embedded and appended to every patch; a learned position embedding tells the
tokens apart; the first `within_view_layers` attend within each view, the rest attend jointly over
all views' tokens and the instruction's tokens.
"""

import torch
from torch import nn

from rvt2cli.model.config import ModelConfig
from rvt2cli.model.transformer import Block
from rvt2cli.render.channels import NUM_CHANNELS


class MultiViewTransformer(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        t = cfg.tokens_per_side
        token_in = cfg.patch_channels + cfg.proprio_channels
        self.patchify = nn.Sequential(
            nn.Conv2d(NUM_CHANNELS, cfg.patch_channels, kernel_size=cfg.patch_size, stride=cfg.patch_size),
            nn.GELU(),
        )
        self.proprio = nn.Sequential(nn.Linear(cfg.proprio_dim, cfg.proprio_channels), nn.GELU())
        self.position = nn.Parameter(torch.randn(len(cfg.views), t * t, token_in) * 0.02)
        self.to_width = nn.Linear(token_in, cfg.width)
        self.lang_in = nn.Linear(cfg.lang_dim, cfg.width)
        self.lang_position = nn.Parameter(torch.randn(cfg.lang_tokens, cfg.width) * 0.02)
        self.blocks = nn.ModuleList(
            Block(cfg.width, cfg.heads, cfg.head_dim, cfg.mlp_ratio, cfg.attention_dropout) for _ in range(cfg.depth)
        )
        self.norm = nn.LayerNorm(cfg.width)

    def forward(self, images: torch.Tensor, proprio: torch.Tensor, lang: torch.Tensor) -> torch.Tensor:
        """images [B, V, 10, H, W], proprio [B, P], lang [B, L, 384] -> features [B, V, width, t, t]."""
        b, v = images.shape[:2]
        t = self.cfg.tokens_per_side
        patches = self.patchify(images.flatten(0, 1))                      # [B*V, C, t, t]
        patches = patches.flatten(2).transpose(1, 2).unflatten(0, (b, v))  # [B, V, t*t, C]
        prop = self.proprio(proprio)[:, None, None, :].expand(b, v, t * t, -1)
        x = self.to_width(torch.cat([patches, prop], dim=-1) + self.position)  # [B, V, t*t, D]
        lang_tokens = self.lang_in(lang) + self.lang_position                 # [B, L, D]

        within = self.cfg.within_view_layers
        x = x.flatten(0, 1)                                                   # [B*V, t*t, D]
        for block in self.blocks[:within]:
            x = block(x)
        x = x.unflatten(0, (b, v)).flatten(1, 2)                              # [B, V*t*t, D]
        n_lang = lang_tokens.shape[1]
        if within < len(self.blocks):
            x = torch.cat([lang_tokens, x], dim=1)
            for block in self.blocks[within:]:
                x = block(x)
            x = x[:, n_lang:]
        x = self.norm(x)
        return x.unflatten(1, (v, t, t)).permute(0, 1, 4, 2, 3)               # [B, V, D, t, t]
