"""Pure-torch reference point renderer: the specification the warp kernels are tested against.

Three steps (paper, "Point-Renderer"):

1. z-buffer: every visible (point, view) gets a 64-bit key (quantised depth << 32 | point index);
   each pixel keeps the smallest key (`scatter_reduce(amin)`): the nearest point, ties broken by
   the lower index.
2. splatting (optional): a pixel takes the smallest key among its own and those of the neighbours
   whose disc (radius r in world units, r*fx pixels orthographic, r*fx/depth pinhole, at most
   `max_splat_px`) covers its centre. It reads the un-splatted z-buffer, so the result does not
   depend on any processing order.
3. gather: unpack each key into the point index (features) and the quantised depth.

Tensor ops only (no Python loop over points or pixels), so it can be traced or exported: keys are
packed with multiplication and unpacked with floor division and remainder (the same bits as shifts
and masks for these non-negative keys; ONNX shifts only unsigned integers), and for export the
splatting window can be given statically (`reach_px`) instead of being read off the cameras.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .cameras import FAR, FX, NEAR, ORTHO, camera_coordinates, pixel_coordinates

EMPTY_KEY = 2**63 - 1  # a pixel no point reached; larger than any key
INDEX_BITS = 32
INDEX_MASK = 2**INDEX_BITS - 1
INDEX_RANGE = 2**INDEX_BITS  # key = level * INDEX_RANGE + index
# q = floor((z - near) / (far - near) * 2^31), clamped to 2^31 - 1. The step is (far - near) / 2^31:
# 2.3e-10 cube units at 4x zoom (far - near = 0.5), far below a millimetre for any real workspace
# (the float32 depth computed before quantising, ~6e-8 relative, is the actual limit).
DEPTH_SCALE = 2.0**31
MAX_DEPTH_LEVEL = 2**31 - 1


def render_reference(
    points: Tensor,
    features: Tensor,
    params: Tensor,
    height: int,
    width: int,
    num_points: Tensor | None = None,
    splat_radius: float = 0.0,
    max_splat_px: int = 8,
    reach_px: int | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Render (validated) clouds; returns features [B, V, H, W, C], depth [B, V, H, W], index [B, V, H, W]."""
    keys = zbuffer(points, params, height, width, num_points)
    if splat_radius > 0:
        keys = splat(keys, params, splat_radius, max_splat_px, reach_px)
    return gather(keys, features, params)


def point_keys(
    points: Tensor, params: Tensor, height: int, width: int, num_points: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Per (view, point): the linear pixel index and the key; EMPTY_KEY (at pixel 0) where not visible."""
    n = points.shape[1]
    x, y, z = camera_coordinates(points, params)
    u, v = pixel_coordinates(x, y, z, params)
    near, far = params[..., NEAR, None], params[..., FAR, None]
    ortho = params[..., ORTHO, None] > 0.5
    index = torch.arange(n, device=points.device)
    visible = (
        torch.isfinite(points).all(-1)[:, None]
        & (z >= near) & (z <= far) & (ortho | (z > 0))
        & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    )
    if num_points is not None:
        visible &= (index < num_points[:, None])[:, None]
    row = torch.where(visible, v.floor(), torch.zeros_like(v)).long()
    col = torch.where(visible, u.floor(), torch.zeros_like(u)).long()
    level = torch.where(visible, ((z - near) / (far - near) * DEPTH_SCALE).floor(), torch.zeros_like(z))
    key = level.long().clamp(0, MAX_DEPTH_LEVEL) * INDEX_RANGE + index
    return row * width + col, torch.where(visible, key, EMPTY_KEY)


def zbuffer(
    points: Tensor, params: Tensor, height: int, width: int, num_points: Tensor | None = None
) -> Tensor:
    """int64 [B, V, H, W]: per pixel the smallest key of the points landing there (EMPTY_KEY if none)."""
    pixel, key = point_keys(points, params, height, width, num_points)
    batch, views = params.shape[:2]
    keys = torch.full((batch, views, height * width), EMPTY_KEY, dtype=torch.int64, device=points.device)
    keys.scatter_reduce_(2, pixel, key, reduce="amin")
    return keys.view(batch, views, height, width)


def key_depth(keys: Tensor, params: Tensor) -> Tensor:
    """Depth [B, V, H, W] dequantised from keys (meaningless where a key is EMPTY_KEY)."""
    near, far = params[..., NEAR, None, None], params[..., FAR, None, None]
    return near + (far - near) * ((keys // INDEX_RANGE).float() / DEPTH_SCALE)


def splat_reach(params: Tensor, splat_radius: float, max_splat_px: int) -> Tensor:
    """Per view, the largest disc radius in pixels (at the near plane for pinhole), capped: [B, V]."""
    radius_px = torch.tensor(splat_radius, dtype=torch.float32, device=params.device) * params[..., FX]
    ortho, near = params[..., ORTHO] > 0.5, params[..., NEAR]
    bound = torch.where(ortho, radius_px, torch.where(near > 0, radius_px / near, math.inf))
    return bound.clamp(max=float(max_splat_px))


def splat(keys: Tensor, params: Tensor, splat_radius: float, max_splat_px: int, reach_px: int | None = None) -> Tensor:
    """Screen-space splatting of a z-buffer [B, V, H, W] (see the module docstring). The window's
    half-width is `reach_px` if given (any value >= the largest disc gives the same result), else
    the largest disc of the cameras (which reads a value off the device)."""
    batch, views, height, width = keys.shape
    if keys.numel() == 0:
        return keys
    reach = reach_px if reach_px is not None else math.ceil(splat_reach(params, splat_radius, max_splat_px).max().item())
    radius_px = torch.tensor(splat_radius, dtype=torch.float32, device=keys.device) * params[..., FX, None, None]
    ortho = params[..., ORTHO, None, None] > 0.5
    disc = torch.where(ortho, radius_px, radius_px / key_depth(keys, params)).clamp(max=float(max_splat_px))
    covered = disc * disc  # squared pixel distance each pixel's disc reaches

    padded_keys = keys.new_full((batch, views, height + 2 * reach, width + 2 * reach), EMPTY_KEY)
    padded_keys[..., reach:reach + height, reach:reach + width] = keys
    padded_covered = covered.new_zeros(padded_keys.shape)
    padded_covered[..., reach:reach + height, reach:reach + width] = covered

    best = keys
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            window = (..., slice(reach + dy, reach + dy + height), slice(reach + dx, reach + dx + width))
            neighbour = padded_keys[window]
            covers = (neighbour != EMPTY_KEY) & (dy * dy + dx * dx <= padded_covered[window])
            best = torch.where(covers, torch.minimum(best, neighbour), best)
    return best


def gather(keys: Tensor, features: Tensor, params: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Unpack keys [B, V, H, W] into features [B, V, H, W, C], depth and index (background 0, 0, -1)."""
    batch, views, height, width = keys.shape
    n, channels = features.shape[1:]
    hit = keys != EMPTY_KEY
    index = torch.where(hit, keys % INDEX_RANGE, -1)
    depth = torch.where(hit, key_depth(keys, params), 0.0)
    # Background pixels gather an appended row of zeros.
    rows = torch.cat([features, features.new_zeros(batch, 1, channels)], 1)
    lookup = torch.where(hit, index, n).view(batch, views * height * width, 1).expand(-1, -1, channels)
    gathered = rows.gather(1, lookup).view(batch, views, height, width, channels)
    return gathered, depth, index
