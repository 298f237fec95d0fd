"""The paper's augmentation: a random yaw (about the vertical axis through the workspace centre) and
a random translation, applied identically to the cloud and to the target pose. The translation is
clamped so the target stays inside the workspace."""

import numpy as np
import torch

from rvt2cli.model.rotation import yaw_rotate_quaternion


def sample_augmentation(n: int, generator: torch.Generator, max_translation: float, max_yaw_deg: float):
    yaw = (torch.rand(n, generator=generator, dtype=torch.float64) * 2 - 1) * np.radians(max_yaw_deg)
    translation = (torch.rand(n, 3, generator=generator, dtype=torch.float64) * 2 - 1) * max_translation
    return yaw.numpy(), translation.numpy()


def yaw_matrices(yaw: np.ndarray) -> np.ndarray:
    """[n] angles (rad) -> [n, 3, 3] rotations about the vertical axis."""
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.zeros((len(yaw), 3, 3))
    m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1], m[:, 2, 2] = c, -s, s, c, 1.0
    return m


def augment_targets(position: np.ndarray, quaternion: np.ndarray, center: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    yaw: np.ndarray, translation: np.ndarray):
    """Rotate and shift targets [n, 3] / [n, 4]; returns (position, quaternion, yaw, translation) where a
    yaw that would push a target out of the workspace is dropped and translations are clamped."""
    rotated = np.einsum("nij,nj->ni", yaw_matrices(yaw), position - center) + center
    outside = np.any((rotated < lo) | (rotated > hi), axis=1)
    yaw = np.where(outside, 0.0, yaw)
    rotated = np.where(outside[:, None], position, rotated)
    translation = np.clip(translation, lo - rotated, hi - rotated)
    return rotated + translation, yaw_rotate_quaternion(quaternion, yaw), yaw, translation


def augment_points(xyz: torch.Tensor, center: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """xyz [B, N, 3] world points -> rotated by `rotation` [B, 3, 3] about `center` [B, 3], then shifted
    by `translation` [B, 3] (all on xyz's device)."""
    return torch.einsum("bij,bnj->bni", rotation, xyz - center[:, None]) + center[:, None] + translation[:, None]
