"""The scene cube: world coordinates (metres) <-> the normalised cube [-1, 1]^3 the renderer sees.

The mapping is isotropic (one scale for all axes), so rotations and distances keep their shape.
"""

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Workspace:
    center: tuple[float, float, float]
    half_extent: float  # metres from the centre to a face

    @staticmethod
    def from_bounds(bounds) -> "Workspace":
        lo, hi = bounds[:3], bounds[3:]
        center = tuple((a + b) / 2 for a, b in zip(lo, hi))
        half = max((b - a) / 2 for a, b in zip(lo, hi))
        return Workspace(center=center, half_extent=half)

    def _center(self, like: torch.Tensor) -> torch.Tensor:
        return torch.tensor(self.center, dtype=like.dtype, device=like.device)

    def to_cube(self, xyz: torch.Tensor) -> torch.Tensor:
        return (xyz - self._center(xyz)) / self.half_extent

    def to_world(self, cube: torch.Tensor) -> torch.Tensor:
        return cube * self.half_extent + self._center(cube)

    def metres_to_cube(self, metres: float) -> float:
        return metres / self.half_extent
