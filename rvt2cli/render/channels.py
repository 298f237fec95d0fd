"""The per-pixel input channels of the network: the one place that decides what the network sees.

For B scenes (points already in cube coordinates, rgb in [0, 1]) and V views, `network_images`
gives float32 [B, V, NUM_CHANNELS, H, W] with channels

    0-2  xyz of the rendered point, cube coordinates              background 0
    3-5  its rgb mapped to [-1, 1]                                background 0
    6    its depth normalised to [0, 1] over [near, far]          background -1
    7-9  pixel location and view: 2 (col + 0.5) / W - 1, 2 (row + 0.5) / H - 1, and the view index
         mapped linearly onto [-1, 1] over the V views (0 when V = 1)
"""

from __future__ import annotations

import torch
from torch import Tensor

from .cameras import Cameras
from .renderer import Rendered, render

NUM_CHANNELS = 10
# Cube units: ~1.3 px in the 224-px views of the whole cube, ~5.4 px at 4x zoom (under the 8-px cap).
DEFAULT_SPLAT_RADIUS = 0.012


def render_scene(
    points: Tensor,
    rgb: Tensor,
    cameras: Cameras,
    image_size: int | tuple[int, int],
    num_points: Tensor | None = None,
    splat_radius: float = DEFAULT_SPLAT_RADIUS,
    backend: str = "warp",
    reach_px: int | None = None,
) -> Rendered:
    """One render of features = (xyz, rgb): Rendered.features[..., :3] is xyz, [..., 3:] rgb."""
    if rgb.shape != points.shape or not rgb.is_floating_point():
        raise ValueError(
            f"rgb must be float in [0, 1], [B, N, 3] like points {tuple(points.shape)}, "
            f"got {tuple(rgb.shape)} {rgb.dtype}"
        )
    features = torch.cat([points, rgb.to(points.dtype)], -1)
    return render(points, features, cameras, image_size, num_points, splat_radius, backend, reach_px=reach_px)


def channels_from_render(rendered: Rendered, cameras: Cameras) -> Tensor:
    """The NUM_CHANNELS images [B, V, 10, H, W] of a `render_scene` result."""
    batch, views, height, width, _ = rendered.features.shape
    hit = rendered.hit.unsqueeze(2)  # [B, V, 1, H, W]
    features = rendered.features.permute(0, 1, 4, 2, 3)  # [B, V, 6, H, W]
    near = cameras.near[..., None, None, None]
    far = cameras.far[..., None, None, None]
    depth = (rendered.depth.unsqueeze(2) - near) / (far - near)

    options = dict(dtype=torch.float32, device=features.device)
    cols = (torch.arange(width, **options) + 0.5) * (2 / width) - 1
    rows = (torch.arange(height, **options) + 0.5) * (2 / height) - 1
    view_ids = torch.linspace(-1, 1, views, **options) if views > 1 else torch.zeros(1, **options)
    location = torch.stack(
        [
            cols.expand(views, height, width),
            rows[:, None].expand(views, height, width),
            view_ids[:, None, None].expand(views, height, width),
        ],
        1,
    )  # [V, 3, H, W]
    return torch.cat(
        [
            features[:, :, :3],
            torch.where(hit, features[:, :, 3:6] * 2 - 1, 0.0),
            torch.where(hit, depth, -1.0),
            location.expand(batch, -1, -1, -1, -1),
        ],
        2,
    )


def network_images(
    points: Tensor,
    rgb: Tensor,
    cameras: Cameras,
    image_size: int | tuple[int, int],
    num_points: Tensor | None = None,
    splat_radius: float = DEFAULT_SPLAT_RADIUS,
    backend: str = "warp",
    reach_px: int | None = None,
) -> Tensor:
    """float32 [B, V, NUM_CHANNELS, H, W]: what the network sees (channel layout above)."""
    rendered = render_scene(points, rgb, cameras, image_size, num_points, splat_radius, backend, reach_px)
    return channels_from_render(rendered, cameras)
