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


def _yaw_matrices(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.zeros((len(yaw), 3, 3))
    m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1], m[:, 2, 2] = c, -s, s, c, 1.0
    return m


def augment_targets(position: np.ndarray, quaternion: np.ndarray, center: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    yaw: np.ndarray, translation: np.ndarray):
    """Rotate and shift targets [n, 3] / [n, 4]; returns (position, quaternion, yaw, translation) where a
    yaw that would push a target out of the workspace is dropped and translations are clamped."""
    rotated = np.einsum("nij,nj->ni", _yaw_matrices(yaw), position - center) + center
    outside = np.any((rotated < lo) | (rotated > hi), axis=1)
    yaw = np.where(outside, 0.0, yaw)
    rotated = np.where(outside[:, None], position, rotated)
    translation = np.clip(translation, lo - rotated, hi - rotated)
    return rotated + translation, yaw_rotate_quaternion(quaternion, yaw), yaw, translation


def augment_points(xyz: torch.Tensor, center: torch.Tensor, yaw: np.ndarray, translation: np.ndarray) -> torch.Tensor:
    """xyz [B, N, 3] world points -> the same rotation about `center` [B, 3] and translation."""
    rot = torch.as_tensor(_yaw_matrices(yaw), dtype=xyz.dtype, device=xyz.device)
    shift = torch.as_tensor(translation, dtype=xyz.dtype, device=xyz.device)
    return torch.einsum("bij,bnj->bni", rot, xyz - center[:, None]) + center[:, None] + shift[:, None]
