"""Rotations as three discrete Euler angles (xyz, 5-degree bins), as RVT and PerAct predict them."""

import numpy as np
from scipy.spatial.transform import Rotation


def quaternion_to_bins(quat_xyzw: np.ndarray, num_bins: int = 72) -> np.ndarray:
    """[..., 4] scalar-last quaternions -> [..., 3] integer bins of the extrinsic xyz Euler angles."""
    quat_xyzw = np.asarray(quat_xyzw, dtype=np.float64)
    euler = Rotation.from_quat(quat_xyzw.reshape(-1, 4)).as_euler("xyz", degrees=True)
    resolution = 360.0 / num_bins
    bins = np.floor((euler + 180.0) / resolution).astype(np.int64) % num_bins
    return bins.reshape(*quat_xyzw.shape[:-1], 3)


def bins_to_quaternion(bins: np.ndarray, num_bins: int = 72) -> np.ndarray:
    """[..., 3] bins -> [..., 4] scalar-last quaternions at the bin centres."""
    bins = np.asarray(bins)
    resolution = 360.0 / num_bins
    euler = -180.0 + (bins.reshape(-1, 3) + 0.5) * resolution
    quat = Rotation.from_euler("xyz", euler, degrees=True).as_quat()
    return quat.reshape(*bins.shape[:-1], 4)


def yaw_rotate_quaternion(quat_xyzw: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
    """Rotate orientations about the world z axis (what the yaw augmentation does to a target)."""
    yaw = np.asarray(yaw_rad, dtype=np.float64).reshape(-1, 1)
    return (Rotation.from_euler("z", yaw) * Rotation.from_quat(np.asarray(quat_xyzw).reshape(-1, 4))).as_quat()


def angle_between(quat_a: np.ndarray, quat_b: np.ndarray) -> np.ndarray:
    """Geodesic angle in degrees between orientations (sign of the quaternion ignored)."""
    a, b = Rotation.from_quat(np.asarray(quat_a).reshape(-1, 4)), Rotation.from_quat(np.asarray(quat_b).reshape(-1, 4))
    return np.degrees((a.inv() * b).magnitude())
