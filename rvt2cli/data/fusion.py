"""RGB-D images -> one world-frame point cloud, cropped to the task's scene bounds.

Episodes store the cameras' RGB-D images; the cloud a policy sees is computed from them by `fuse`,
deterministically, in recording, training and evaluation alike.
"""

import numpy as np
from scipy.spatial.transform import Rotation

from rvt2cli.data.episode import CameraFrame, Cloud


# rvt2's intrinsics (SAPIEN's) put pixel edges on integer image coordinates: pixel (row, col) is
# sampled at (col + 0.5, row + 0.5). OpenCV and ROS put pixel centres there, so between the two
# conventions the principal point moves by half a pixel.
_HALF_PIXEL = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [0.0, 0.0, 0.0]])


def intrinsic_from_opencv(K) -> np.ndarray:
    """rvt2's K of a camera whose K follows OpenCV's (and ROS's) convention."""
    return np.asarray(K, dtype=np.float64).reshape(3, 3) + _HALF_PIXEL


def intrinsic_to_opencv(K) -> np.ndarray:
    return np.asarray(K, dtype=np.float64).reshape(3, 3) - _HALF_PIXEL


def depth_in_metres(depth: np.ndarray) -> np.ndarray:
    """float32 metres from a depth image in metres (float) or millimetres (uint16, as RealSense gives it);
    non-finite and non-positive values are 0 (no return)."""
    depth = np.asarray(depth)
    metres = depth.astype(np.float32) * np.float32(0.001) if depth.dtype == np.uint16 else depth.astype(np.float32)
    return np.where(np.isfinite(metres) & (metres > 0), metres, np.float32(0.0)).astype(np.float32)


def camera_points(cam: CameraFrame) -> Cloud:
    """Back-project every pixel with a depth return into the world frame.

    Pixel (row, col) is sampled at its centre (col + 0.5, row + 0.5): SAPIEN's intrinsics put the
    principal point at W/2, i.e. pixel edges sit on integer coordinates.
    """
    # flat indices rather than 2D ones: the same points, in the same order, in fewer and cheaper numpy passes
    # (training reads every sample's cloud this way, and evaluation fuses two clouds a keyframe)
    depth = cam.depth.reshape(-1)
    pixels = np.flatnonzero(depth > 0)
    rows, cols = np.divmod(pixels, cam.depth.shape[1])
    z = depth[pixels].astype(np.float64)
    K = cam.intrinsic
    x = (cols + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (rows + 0.5 - K[1, 2]) / K[1, 1] * z
    rotation = Rotation.from_quat(cam.cam2world[3:]).as_matrix()
    world = np.stack([x, y, z], axis=1) @ rotation.T + cam.cam2world[:3]
    return Cloud(xyz=world.astype(np.float32), rgb=cam.rgb.reshape(-1, 3)[pixels])


def crop(cloud: Cloud, bounds) -> Cloud:
    lo, hi = np.asarray(bounds[:3], np.float32), np.asarray(bounds[3:], np.float32)
    xyz = cloud.xyz
    keep = np.ones(len(xyz), dtype=bool)
    for axis in range(3):  # column by column: no [N, 3] temporaries and no reduction over rows
        keep &= (xyz[:, axis] >= lo[axis]) & (xyz[:, axis] <= hi[axis])
    return Cloud(xyz=xyz[keep], rgb=cloud.rgb[keep])


def voxel_downsample(cloud: Cloud, voxel_size: float) -> Cloud:
    """One point per occupied voxel (mean position and colour), with open3d."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(cloud.xyz.astype(np.float64))
    pcd.colors = o3d.utility.Vector3dVector(cloud.rgb.astype(np.float64) / 255.0)
    down = pcd.voxel_down_sample(voxel_size)
    xyz = np.asarray(down.points, dtype=np.float32)
    rgb = np.clip(np.rint(np.asarray(down.colors) * 255.0), 0, 255).astype(np.uint8)
    return Cloud(xyz=xyz, rgb=rgb)


def fuse(cameras: dict[str, CameraFrame], bounds, voxel_size: float | None = None) -> Cloud:
    """All cameras' points in the world frame, cropped to `bounds`, optionally voxel-downsampled."""
    parts = [crop(camera_points(cam), bounds) for cam in cameras.values()]
    cloud = Cloud(xyz=np.concatenate([p.xyz for p in parts]), rgb=np.concatenate([p.rgb for p in parts]))
    if voxel_size:
        cloud = voxel_downsample(cloud, voxel_size)
    return cloud
