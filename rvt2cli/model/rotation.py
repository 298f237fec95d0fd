"""Rotations as three discrete Euler angles (xyz, 5-degree bins), as RVT and PerAct predict them.

The network scores `rotation_bins` bins per axis; a prediction decodes to its best bin refined by its
neighbours' scores (`decode_euler`): a 5-degree bin centre is up to 2.5 degrees off per axis, while
the expert's own insert_peg keyframes, turned by 1 degree, insert the peg in 25% of episodes and by
half a degree in 56% (rvt2 diagnose precision-budget).

Training targets are the true bin (the paper), or with `rotation_sigma_deg` > 0 a circular Gaussian
over the bins centred on the true angle itself (`soft_bin_targets`, "circular smooth labels"): fine bins
then share what their neighbours learn, and the scores' centroid (`decode_window` bins either side of
the best) recovers the angle between bin centres.
"""

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation


def quaternion_to_euler(quat_xyzw: np.ndarray) -> np.ndarray:
    """[..., 4] scalar-last quaternions -> [..., 3] extrinsic xyz Euler angles in degrees, in [-180, 180]."""
    quat_xyzw = np.asarray(quat_xyzw, dtype=np.float64)
    return Rotation.from_quat(quat_xyzw.reshape(-1, 4)).as_euler("xyz", degrees=True).reshape(*quat_xyzw.shape[:-1], 3)


def euler_to_bins(euler_deg: np.ndarray, num_bins: int = 72) -> np.ndarray:
    """[..., 3] Euler angles in degrees -> [..., 3] integer bins."""
    return np.floor((np.asarray(euler_deg) + 180.0) / (360.0 / num_bins)).astype(np.int64) % num_bins


def quaternion_to_bins(quat_xyzw: np.ndarray, num_bins: int = 72) -> np.ndarray:
    """[..., 4] scalar-last quaternions -> [..., 3] integer bins of the extrinsic xyz Euler angles."""
    return euler_to_bins(quaternion_to_euler(quat_xyzw), num_bins)


def bin_centre_deg(index, num_bins: int):
    """Bin `index` (an integer, or fractional: between centres) -> its angle in degrees; numpy or torch."""
    return -180.0 + (index + 0.5) * (360.0 / num_bins)


def soft_bin_targets(euler_deg: torch.Tensor, num_bins: int, sigma_deg: float) -> torch.Tensor:
    """[B, 3] Euler angles (degrees) -> [B, 3, num_bins] target distributions: a Gaussian of `sigma_deg`
    around each angle over the bin centres, wrapped around +-180 degrees, summing to 1 per axis."""
    centres = bin_centre_deg(torch.arange(num_bins, device=euler_deg.device, dtype=torch.float32), num_bins)
    gap = torch.remainder(centres - euler_deg.float()[..., None] + 180.0, 360.0) - 180.0
    return torch.softmax(-0.5 * (gap / sigma_deg) ** 2, dim=-1)


def decode_window(num_bins: int, sigma_deg: float) -> int:
    """Bins either side of the best that `decode_euler` averages over: one for one-bin targets, two
    standard deviations of soft targets."""
    return max(1, math.ceil(2 * sigma_deg / (360.0 / num_bins)))


def bins_to_quaternion(bins: np.ndarray, num_bins: int = 72) -> np.ndarray:
    """[..., 3] bins -> [..., 4] scalar-last quaternions at the bin centres."""
    bins = np.asarray(bins)
    quat = Rotation.from_euler("xyz", bin_centre_deg(bins.reshape(-1, 3), num_bins), degrees=True).as_quat()
    return quat.reshape(*bins.shape[:-1], 4)


def yaw_rotate_quaternion(quat_xyzw: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
    """Rotate orientations about the world z axis (what the yaw augmentation does to a target)."""
    yaw = np.asarray(yaw_rad, dtype=np.float64).reshape(-1, 1)
    return (Rotation.from_euler("z", yaw) * Rotation.from_quat(np.asarray(quat_xyzw).reshape(-1, 4))).as_quat()


def angle_between(quat_a: np.ndarray, quat_b: np.ndarray) -> np.ndarray:
    """Geodesic angle in degrees between orientations (sign of the quaternion ignored)."""
    a, b = Rotation.from_quat(np.asarray(quat_a).reshape(-1, 4)), Rotation.from_quat(np.asarray(quat_b).reshape(-1, 4))
    return np.degrees((a.inv() * b).magnitude())


def decode_euler(logits: list[torch.Tensor], refine: bool = True, window: int = 1) -> torch.Tensor:
    """Three [B, bins] score tensors (x, y, z) -> [B, 3] extrinsic xyz Euler angles in radians: the best
    bin's centre moved by the centroid of the softmax over the `window` bins either side of it
    (cyclically); with one, p(k+1) - p(k-1) of a bin. One-bin targets score an angle near a bin's edge
    in both bins it lies between, soft targets in a Gaussian around it: either way the centroid places
    it within the bin. `refine=False`: the bin centres (as RVT and PerAct decode)."""
    angles = []
    for scores in logits:
        bins = scores.shape[-1]
        best = scores.argmax(-1, keepdim=True)
        steps = torch.arange(-window, window + 1, device=scores.device)
        share = torch.softmax(scores.float().gather(-1, (best + steps) % bins), dim=-1)
        offset = (share * steps.float()).sum(-1) if refine else torch.zeros_like(share[:, 0])
        angles.append(torch.deg2rad(bin_centre_deg(best[:, 0].float() + offset, bins)))
    return torch.stack(angles, dim=-1)


def euler_to_quaternion(angles: torch.Tensor) -> torch.Tensor:
    """[B, 3] extrinsic xyz Euler angles (radians) -> [B, 4] quaternions x y z w (torch: exportable)."""
    half = angles.float() / 2
    c, s = torch.cos(half), torch.sin(half)
    cx, cy, cz, sx, sy, sz = c[:, 0], c[:, 1], c[:, 2], s[:, 0], s[:, 1], s[:, 2]
    # q = q_z * q_y * q_x (extrinsic x, then y, then z)
    w = cz * cy * cx + sz * sy * sx
    x = cz * cy * sx - sz * sy * cx
    y = cz * sy * cx + sz * cy * sx
    z = sz * cy * cx - cz * sy * sx
    return torch.stack([x, y, z, w], dim=-1)


def rotate_vectors(quat_xyzw: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
    """[B, 4] quaternions (x y z w) applied to [B, 3] vectors (torch: exportable)."""
    q, w = quat_xyzw[:, :3], quat_xyzw[:, 3:]
    twice_cross = 2 * torch.cross(q, vectors, dim=-1)
    return vectors + w * twice_cross + torch.cross(q, twice_cross, dim=-1)
