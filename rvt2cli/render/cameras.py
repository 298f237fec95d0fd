"""Virtual cameras: batches of them, the rigs RVT-2 looks at the scene cube with, and projection.

A camera is 19 numbers (the columns of `Cameras.params`):

    R (9, row-major, world -> camera), t (3), fx, fy, cx, cy, near, far, ortho

with p_cam = R p + t in the OpenCV camera frame (x right, y down, z forward; depth = z_cam) and

    orthographic (ortho = 1):  u = fx x + cx,        v = fy y + cy
    pinhole      (ortho = 0):  u = fx x / z + cx,    v = fy y / z + cy    (only for z > 0)

A point lands in pixel (row, col) = (floor(v), floor(u)) when it is inside the image and
near <= z <= far; pixel (row, col) has its centre at (u, v) = (col + 0.5, row + 0.5).
"""

from __future__ import annotations

import functools

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

NUM_PARAMS = 19
ROTATION = slice(0, 9)
TRANSLATION = slice(9, 12)
FX, FY, CX, CY, NEAR, FAR, ORTHO = range(12, 19)

# Image axes of each view in world (= cube) coordinates, z up: (right, down, viewing direction).
VIEW_AXES: dict[str, tuple[tuple[float, float, float], ...]] = {
    "top": ((0, -1, 0), (-1, 0, 0), (0, 0, -1)),
    "front": ((0, 1, 0), (0, 0, -1), (-1, 0, 0)),   # camera at +x looking toward -x
    "right": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),    # camera at -y looking toward +y
    "back": ((0, -1, 0), (0, 0, -1), (1, 0, 0)),    # camera at -x looking toward +x
    "left": ((-1, 0, 0), (0, 0, -1), (0, -1, 0)),   # camera at +y looking toward -y
}
RVT2_VIEWS = ("top", "front", "right")
RVT1_VIEWS = ("top", "front", "back", "left", "right")


@dataclass(frozen=True)
class Cameras:
    """A batch of V cameras for each of B scenes: `params` float32 [B, V, 19] (layout above)."""

    params: Tensor

    def __post_init__(self) -> None:
        p = self.params
        if not isinstance(p, Tensor) or p.dtype != torch.float32 or p.ndim != 3 or p.shape[-1] != NUM_PARAMS:
            shape = tuple(p.shape) if isinstance(p, Tensor) else type(p).__name__
            dtype = p.dtype if isinstance(p, Tensor) else None
            raise ValueError(f"Cameras.params must be float32 [B, V, {NUM_PARAMS}], got {shape} {dtype}")

    @classmethod
    def create(
        cls,
        rotation: Tensor,
        translation: Tensor,
        fx: float | Tensor,
        fy: float | Tensor,
        cx: float | Tensor,
        cy: float | Tensor,
        near: float | Tensor,
        far: float | Tensor,
        ortho: bool | Tensor,
    ) -> Cameras:
        """Cameras from rotation [B, V, 3, 3] and translation [B, V, 3]; the other numbers are scalars
        or tensors that broadcast to [B, V]."""
        if rotation.ndim != 4 or rotation.shape[-2:] != (3, 3):
            raise ValueError(f"rotation must be [B, V, 3, 3], got {tuple(rotation.shape)}")
        batch_views = rotation.shape[:2]
        if translation.shape != (*batch_views, 3):
            raise ValueError(f"translation must be {(*batch_views, 3)}, got {tuple(translation.shape)}")
        options = dict(dtype=torch.float32, device=rotation.device)
        scalars = [
            torch.as_tensor(x, **options).expand(batch_views).unsqueeze(-1)
            for x in (fx, fy, cx, cy, near, far, ortho)
        ]
        params = torch.cat([rotation.reshape(*batch_views, 9).to(**options), translation.to(**options), *scalars], -1)
        return cls(params.contiguous())

    @property
    def batch_size(self) -> int:
        return self.params.shape[0]

    @property
    def num_views(self) -> int:
        return self.params.shape[1]

    @property
    def device(self) -> torch.device:
        return self.params.device

    @property
    def rotation(self) -> Tensor:
        """[B, V, 3, 3], world -> camera."""
        return self.params[..., ROTATION].unflatten(-1, (3, 3))

    @property
    def translation(self) -> Tensor:
        """[B, V, 3]."""
        return self.params[..., TRANSLATION]

    @property
    def near(self) -> Tensor:
        """[B, V]."""
        return self.params[..., NEAR]

    @property
    def far(self) -> Tensor:
        """[B, V]."""
        return self.params[..., FAR]

    @property
    def is_ortho(self) -> Tensor:
        """bool [B, V]."""
        return self.params[..., ORTHO] > 0.5

    def to(self, device: torch.device | str) -> Cameras:
        return Cameras(self.params.to(device))

    def __len__(self) -> int:
        return self.batch_size

    def __getitem__(self, index: int | slice | Tensor) -> Cameras:
        """Select scenes along the batch; an int keeps the batch dimension (size 1)."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        return Cameras(self.params[index])

    @staticmethod
    def cat(cameras: Sequence[Cameras]) -> Cameras:
        """Concatenate along the batch (all must have the same number of views)."""
        return Cameras(torch.cat([c.params for c in cameras], 0))


def _tracing() -> bool:
    """Inside torch.export / torch.compile / TorchScript tracing (tensors made there must not be cached)."""
    return torch.compiler.is_compiling() or torch._guards.detect_fake_mode() is not None or torch.jit.is_tracing()


def _rig_template(views: tuple[str, ...], image_size: int, zoom: float, device: torch.device) -> tuple[Tensor, Tensor]:
    """The parts of a rig that do not depend on its centre: rotations [V, 3, 3] and the 7 trailing
    parameters [V, 7]. Cached per device, so building a rig copies nothing from the host (a CUDA
    graph can capture it); not cached while tracing, where tensors are placeholders."""
    if _tracing():
        return _build_rig_template(views, image_size, zoom, device)
    return _cached_rig_template(views, image_size, zoom, device)


def _build_rig_template(views: tuple[str, ...], image_size: int, zoom: float, device: torch.device) -> tuple[Tensor, Tensor]:
    unknown = [v for v in views if v not in VIEW_AXES]
    if unknown or not views:
        raise ValueError(f"unknown views {unknown}; known: {sorted(VIEW_AXES)}")
    rotation = torch.tensor([VIEW_AXES[v] for v in views], dtype=torch.float32, device=device)
    half = image_size / 2
    trailing = torch.tensor([[half * zoom, half * zoom, half, half, 0.0, 2.0 / zoom, 1.0]] * len(views),
                            dtype=torch.float32, device=device)
    return rotation, trailing


_cached_rig_template = functools.lru_cache(maxsize=64)(_build_rig_template)


def zoom_rig(
    centers: Tensor,
    zoom: float = 4.0,
    views: Sequence[str] = RVT2_VIEWS,
    image_size: int = 224,
) -> Cameras:
    """Orthographic views of the axis-aligned boxes centers[b] +- 1/zoom, one rig per row of centers [B, 3].

    Each camera sits on the box face it looks through (origin = center - direction / zoom), so depth
    runs over [0, 2 / zoom]. With fx = fy = W/2 * zoom and cx = cy = W/2 a pixel is 2 / (W zoom) wide
    and the pixel centres of all views line up with one grid of W^3 voxel centres over the box.
    """
    if centers.ndim != 2 or centers.shape[-1] != 3:
        raise ValueError(f"centers must be [B, 3], got {tuple(centers.shape)}")
    if not isinstance(image_size, int) or image_size <= 0:
        raise ValueError(f"a rig's image_size must be a positive int (square images), got {image_size!r}")
    rotation, trailing = _rig_template(tuple(views), image_size, float(zoom), centers.device)
    batch, n_views = centers.shape[0], len(views)
    # t = -R (center - direction / zoom) = -R center + (0, 0, 1 / zoom), because R direction = z axis.
    translation = -torch.einsum("vij,bj->bvi", rotation, centers.to(torch.float32))
    translation = translation + torch.cat([translation.new_zeros(2), translation.new_full((1,), 1.0 / zoom)])
    params = torch.cat([rotation.reshape(1, n_views, 9).expand(batch, -1, -1), translation,
                        trailing.expand(batch, -1, -1)], -1)
    return Cameras(params.contiguous())


def cube_rig(
    views: Sequence[str] = RVT2_VIEWS,
    image_size: int = 224,
    batch_size: int = 1,
    device: torch.device | str = "cpu",
) -> Cameras:
    """Orthographic views that exactly cover the cube [-1, 1]^3 (depth over [0, 2])."""
    return zoom_rig(torch.zeros(batch_size, 3, device=device), zoom=1.0, views=views, image_size=image_size)


def camera_coordinates(points: Tensor, params: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """p_cam = R p + t for every (view, point): three tensors [B, V, N].

    Written as explicit products and sums, in the same order as the warp kernel, so that both
    backends round identically (warp is compiled without FMA contraction)."""
    p = points[:, None]  # [B, 1, N, 3]
    r = params[..., None, :]  # [B, V, 1, 19]
    return tuple(
        r[..., 3 * i] * p[..., 0] + r[..., 3 * i + 1] * p[..., 1] + r[..., 3 * i + 2] * p[..., 2] + r[..., 9 + i]
        for i in range(3)
    )


def pixel_coordinates(x: Tensor, y: Tensor, z: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """Continuous pixel coordinates (u, v) [B, V, N] of camera-frame points (meaningless for pinhole z <= 0)."""
    r = params[..., None, :]
    divisor = torch.where(r[..., ORTHO] > 0.5, torch.ones_like(z), z)
    return r[..., FX] * x / divisor + r[..., CX], r[..., FY] * y / divisor + r[..., CY]


def project(points: Tensor, cameras: Cameras) -> tuple[Tensor, Tensor]:
    """Project points [B, N, 3] into every view: uv [B, V, N, 2] (continuous pixel coordinates) and
    depth [B, V, N]. Plain torch, no visibility test: the renderer's pixel of a visible point is
    (floor(v), floor(u))."""
    if points.ndim != 3 or points.shape[-1] != 3 or points.shape[0] != cameras.batch_size:
        raise ValueError(f"points must be [B={cameras.batch_size}, N, 3], got {tuple(points.shape)}")
    x, y, z = camera_coordinates(points.to(torch.float32), cameras.params)
    u, v = pixel_coordinates(x, y, z, cameras.params)
    return torch.stack([u, v], -1), z
