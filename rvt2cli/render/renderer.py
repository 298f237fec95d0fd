"""`render(...)`: the public entry point of the point renderer; checks the inputs and picks a backend."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .cameras import Cameras
from .reference import INDEX_BITS, render_reference

BACKENDS = ("warp", "torch")
MAX_POINTS = 2 ** (INDEX_BITS - 1) - 1  # point indices live in the key's low 32 bits; warp indexes with int32


@dataclass
class Rendered:
    """What a render produces, per scene b, view v and pixel (row, col)."""

    features: Tensor  # float32 [B, V, H, W, C], the nearest point's features; background 0
    depth: Tensor  # float32 [B, V, H, W], its depth z_cam (quantised to (far - near) / 2^31); background 0
    index: Tensor  # int64 [B, V, H, W], its index within its cloud; background -1

    @property
    def hit(self) -> Tensor:
        """bool [B, V, H, W]: pixels some point reached."""
        return self.index >= 0


def render(
    points: Tensor,
    features: Tensor,
    cameras: Cameras,
    image_size: int | tuple[int, int],
    num_points: Tensor | None = None,
    splat_radius: float = 0.0,
    backend: str = "warp",
    max_splat_px: int = 8,
    reach_px: int | None = None,
) -> Rendered:
    """Render B point clouds into the V views of `cameras`.

    points float32 [B, N, 3] and features float32 [B, N, C] (C >= 1), in the cameras' world frame;
    num_points int64 [B] (optional): points at index >= num_points[b] are ignored. Points with a
    non-finite coordinate are dropped. splat_radius (world units, 0 = off) draws each point as a
    camera-facing disc; discs wider than max_splat_px pixels are shrunk to that radius.
    backend "warp" runs the kernels, "torch" the reference; both give identical index images.
    reach_px (torch backend): a static splatting window half-width, at least the largest disc, so
    the reference reads nothing off the device (tracing, export, CUDA graphs).
    """
    height, width = _image_shape(image_size)
    _check_inputs(points, features, cameras, num_points)
    if not (math.isfinite(splat_radius) and splat_radius >= 0):
        raise ValueError(f"splat_radius must be finite and >= 0, got {splat_radius}")
    if not isinstance(max_splat_px, int) or max_splat_px < 0:
        raise ValueError(f"max_splat_px must be an int >= 0, got {max_splat_px!r}")
    extra = {}
    if backend == "warp":
        from .warp_renderer import render_warp as backend_render  # imports warp only when used
    elif backend == "torch":
        backend_render, extra = render_reference, {"reach_px": reach_px}
    else:
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    images = backend_render(
        points.contiguous(), features.contiguous(), cameras.params.contiguous(), height, width,
        None if num_points is None else num_points.contiguous(), float(splat_radius), max_splat_px, **extra,
    )
    return Rendered(*images)


def _image_shape(image_size: int | tuple[int, int]) -> tuple[int, int]:
    size = (image_size, image_size) if isinstance(image_size, int) else tuple(image_size)
    if len(size) != 2 or not all(isinstance(s, int) and s > 0 for s in size):
        raise ValueError(f"image_size must be a positive int or (H, W), got {image_size!r}")
    return size


def _check_inputs(points: Tensor, features: Tensor, cameras: Cameras, num_points: Tensor | None) -> None:
    if not isinstance(cameras, Cameras):
        raise ValueError(f"cameras must be a Cameras, got {type(cameras).__name__}")
    if points.dtype != torch.float32 or points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f"points must be float32 [B, N, 3], got {tuple(points.shape)} {points.dtype}")
    batch, n = points.shape[:2]
    wrong_features = features.dtype != torch.float32 or features.ndim != 3 or features.shape[:2] != (batch, n)
    if wrong_features or features.shape[2] == 0:
        raise ValueError(
            f"features must be float32 [B, N, C>=1] matching points {tuple(points.shape)}, "
            f"got {tuple(features.shape)} {features.dtype}"
        )
    if cameras.batch_size != batch:
        raise ValueError(
            f"cameras {tuple(cameras.params.shape)} must have the batch size of points {tuple(points.shape)}"
        )
    if n > MAX_POINTS:
        raise ValueError(f"at most {MAX_POINTS} points per cloud, got {n}")
    if num_points is not None and (num_points.dtype != torch.int64 or num_points.shape != (batch,)):
        raise ValueError(f"num_points must be int64 [B={batch}], got {tuple(num_points.shape)} {num_points.dtype}")
    devices = {t.device for t in (points, features, cameras.params, num_points) if t is not None}
    if len(devices) > 1:
        raise ValueError(
            f"points, features, cameras and num_points must be on one device, got {sorted(map(str, devices))}"
        )
