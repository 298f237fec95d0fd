"""The scene cube: world coordinates (metres) <-> the normalised cube [-1, 1]^3 the renderer sees.

The cube is centred on the scene bounds' centre and its half extent is the bounds' largest half
extent: the mapping is isotropic (one scale for all axes), so rotations and distances keep their shape.
"""

from dataclasses import dataclass

import numpy as np
import torch


def center_and_half(bounds):
    """Scene bounds (xmin ymin zmin xmax ymax zmax) -> (centre [3], half extent), for a numpy array or a
    torch tensor alike (the exported policy computes it inside its graph)."""
    lo, hi = bounds[:3], bounds[3:]
    return (lo + hi) / 2, ((hi - lo) / 2).max()


@dataclass(frozen=True)
class Workspace:
    center: tuple[float, float, float]
    half_extent: float  # metres from the centre to a face

    @staticmethod
    def from_bounds(bounds) -> "Workspace":
        center, half = center_and_half(np.asarray(bounds, dtype=np.float64))
        return Workspace(center=tuple(float(c) for c in center), half_extent=float(half))

    def _center(self, like: torch.Tensor) -> torch.Tensor:
        return torch.tensor(self.center, dtype=like.dtype, device=like.device)

    def to_cube(self, xyz: torch.Tensor) -> torch.Tensor:
        return (xyz - self._center(xyz)) / self.half_extent

    def to_world(self, cube: torch.Tensor) -> torch.Tensor:
        return cube * self.half_extent + self._center(cube)

    def metres_to_cube(self, metres: float) -> float:
        return metres / self.half_extent
