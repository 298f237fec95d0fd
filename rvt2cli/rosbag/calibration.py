"""A camera's sensor_msgs/CameraInfo -> rvt2's pinhole intrinsics, undistorting the images first.

rvt2 back-projects depth through a pinhole K (rvt2cli.data.fusion). A camera with lens distortion
(`plumb_bob`, `rational_polynomial`, `equidistant`: Azure Kinect, ZED, OAK-D) has its colour and
depth images remapped by OpenCV onto the pinhole camera its CameraInfo's P describes (the rectified
camera, as ROS's image_proc rectifies), and that camera's intrinsics go into the episode. Depth is
remapped by nearest neighbour, so that no depth is made up between an object and its background;
a pixel's depth is along the optical axis, which undistortion does not change. A camera without
distortion (all coefficients zero: most RealSense colour streams) is taken as it is, with K.
"""

from dataclasses import dataclass

import cv2
import numpy as np

from rvt2cli.data.fusion import intrinsic_from_opencv

DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant")


def _field(info, name: str):
    """A CameraInfo field: ROS 2 spells them d, k, r, p; ROS 1 D, K, R, P."""
    return getattr(info, name) if hasattr(info, name) else getattr(info, name.upper())


def camera_matrix(info) -> np.ndarray:
    """K [3, 3] in OpenCV's (and ROS's) convention: pixel centres on integers."""
    return np.asarray(_field(info, "k"), dtype=np.float64).reshape(3, 3)


def distortion(info) -> np.ndarray:
    return np.asarray(_field(info, "d"), dtype=np.float64).ravel()


def distortion_problem(info) -> str | None:
    """Why rvt2 cannot undistort this camera's images, or None."""
    coefficients = distortion(info)
    if not np.any(coefficients):
        return None
    if info.distortion_model not in DISTORTION_MODELS:
        return (f"distortion model '{info.distortion_model}' is not one rvt2 undistorts "
                f"({', '.join(DISTORTION_MODELS)})")
    wanted = {"plumb_bob": (5,), "rational_polynomial": (8, 5), "equidistant": (4,)}[info.distortion_model]
    if len(coefficients) not in wanted:
        return f"{info.distortion_model} distortion with {len(coefficients)} coefficients (expected {wanted[0]})"
    return None


@dataclass
class Undistortion:
    """Remaps one camera's images onto its pinhole camera; `intrinsic` is that camera's rvt2 K."""

    intrinsic: np.ndarray
    maps: tuple[np.ndarray, np.ndarray] | None   # None: no distortion, images are kept as they are

    @staticmethod
    def of(info, size: tuple[int, int]) -> "Undistortion":
        """For a camera with this CameraInfo and images of `size` (width, height)."""
        K, coefficients = camera_matrix(info), distortion(info)
        if not np.any(coefficients):
            return Undistortion(intrinsic_from_opencv(K), None)
        P = np.asarray(_field(info, "p"), dtype=np.float64).reshape(3, 4)[:, :3]
        pinhole = P if P[0, 0] > 0 and P[1, 1] > 0 else K
        if info.distortion_model == "equidistant":
            maps = cv2.fisheye.initUndistortRectifyMap(K, coefficients[:4], np.eye(3), pinhole, size, cv2.CV_32FC1)
        else:
            maps = cv2.initUndistortRectifyMap(K, coefficients, None, pinhole, size, cv2.CV_32FC1)
        return Undistortion(intrinsic_from_opencv(pinhole), maps)

    def colour(self, rgb: np.ndarray) -> np.ndarray:
        if self.maps is None:
            return rgb
        return cv2.remap(rgb, *self.maps, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        if self.maps is None:
            return depth
        return cv2.remap(depth, *self.maps, interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
