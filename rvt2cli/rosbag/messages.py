"""The ROS message types rvt2 reads, and building them from numpy for a bag of a given distribution.

The definitions themselves come from `rosbags`' typestores, which hold every standard message of
each ROS distribution: ROS 1 Noetic, ROS 2 Humble and Jazzy. ROS 1 and ROS 2 spell a few things
apart (a Header's `seq`, CameraInfo's `D K R P` for ROS 2's `d k r p`); `Messages` hides that.
"""

import struct

import cv2
import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from rvt2cli.data.fusion import intrinsic_to_opencv

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
JOINT_STATE = "sensor_msgs/msg/JointState"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

DISTROS = {"noetic": Stores.ROS1_NOETIC, "humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}
COMPRESSED_DEPTH_PNG = 0   # compressed_depth_image_transport's compressionFormat enum: PNG


class Messages:
    """Builds and serialises the messages of one ROS distribution."""

    def __init__(self, distro: str):
        self.distro = distro
        self.ros1 = distro == "noetic"
        self.store = get_typestore(DISTROS[distro])
        if TF_MESSAGE not in self.store.types:
            # rosbags' Noetic store lacks tf2_msgs, whose one message ROS 1's /tf and /tf_static carry
            self.store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE))
        self.types = self.store.types

    def serialize(self, msg, datatype: str) -> bytes:
        return self.store.serialize_ros1(msg, datatype) if self.ros1 else self.store.serialize_cdr(msg, datatype)

    def header(self, t_ns: int, frame_id: str):
        sec, nanosec = divmod(int(t_ns), 1_000_000_000)
        stamp = self.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        extra = {"seq": 0} if self.ros1 else {}
        return self.types["std_msgs/msg/Header"](**extra, stamp=stamp, frame_id=frame_id)

    def image(self, array: np.ndarray, encoding: str, t_ns: int, frame_id: str):
        """A sensor_msgs/Image from an RGB uint8 [H, W, 3] image (`rgb8`, `bgr8`, `rgba8`, `bgra8`) or a depth [H, W] in
        metres (`32FC1`, `16UC1` in millimetres)."""
        pixels = _pixels(array, encoding)
        height, width = pixels.shape[:2]
        data = np.frombuffer(np.ascontiguousarray(pixels).tobytes(), np.uint8)
        return self.types[IMAGE](header=self.header(t_ns, frame_id), height=height, width=width, encoding=encoding,
                                 is_bigendian=0, step=len(data) // height, data=data)

    def compressed_colour(self, rgb: np.ndarray, kind: str, t_ns: int, frame_id: str):
        """image_transport's `compressed` of an rgb8 image: a JPEG or a PNG of its BGR pixels."""
        ok, data = cv2.imencode(f".{'jpg' if kind == 'jpeg' else kind}", np.ascontiguousarray(rgb[..., ::-1]))
        assert ok
        return self.types[COMPRESSED_IMAGE](header=self.header(t_ns, frame_id), format=f"rgb8; {kind} compressed bgr8",
                                            data=data.ravel())

    def compressed_depth(self, depth: np.ndarray, t_ns: int, frame_id: str):
        """image_transport's `compressedDepth` of a 16UC1 image: the 12-byte header and a 16-bit PNG."""
        ok, png = cv2.imencode(".png", _pixels(depth, "16UC1"))
        assert ok
        data = struct.pack("<iff", COMPRESSED_DEPTH_PNG, 0.0, 0.0) + png.tobytes()
        return self.types[COMPRESSED_IMAGE](header=self.header(t_ns, frame_id), format="16UC1; compressedDepth png",
                                            data=np.frombuffer(data, np.uint8))

    def camera_info(self, K: np.ndarray, width: int, height: int, t_ns: int, frame_id: str,
                    model: str = "plumb_bob", coefficients=(0.0,) * 5):
        """A sensor_msgs/CameraInfo from rvt2's K (pixel edges on integers)."""
        K = intrinsic_to_opencv(K)
        P = np.zeros((3, 4))
        P[:, :3] = K
        d, k, r, p = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        roi = self.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.types[CAMERA_INFO](
            header=self.header(t_ns, frame_id), height=height, width=width, distortion_model=model,
            **{d: np.asarray(coefficients, np.float64), k: K.ravel(), r: np.eye(3).ravel(), p: P.ravel()},
            binning_x=0, binning_y=0, roi=roi)

    def joint_state(self, names, positions, velocities, t_ns: int):
        return self.types[JOINT_STATE](header=self.header(t_ns, ""), name=list(names),
                                       position=np.asarray(positions, np.float64), velocity=np.asarray(velocities, np.float64),
                                       effort=np.zeros(0))

    def transforms(self, stamped: list[tuple[str, str, tuple, int]]):
        """A tf2_msgs/TFMessage of (parent, child, pose x y z qx qy qz qw, stamp) transforms."""
        types = self.types
        out = []
        for parent, child, pose, t_ns in stamped:
            x, y, z, qx, qy, qz, qw = (float(v) for v in pose)
            transform = types["geometry_msgs/msg/Transform"](
                translation=types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
                rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))
            out.append(types["geometry_msgs/msg/TransformStamped"](header=self.header(t_ns, parent), child_frame_id=child,
                                                                   transform=transform))
        return types[TF_MESSAGE](transforms=out)


def _pixels(array: np.ndarray, encoding: str) -> np.ndarray:
    if encoding == "rgb8":
        return np.asarray(array, np.uint8)
    if encoding == "bgr8":
        return np.asarray(array, np.uint8)[..., ::-1]
    if encoding in ("rgba8", "bgra8"):
        alpha = np.full(np.shape(array)[:2] + (1,), 255, np.uint8)
        return np.concatenate([_pixels(array, encoding[:3] + "8"), alpha], axis=-1)
    if encoding == "32FC1":
        return np.asarray(array, "<f4")
    if encoding == "16UC1":
        return np.clip(np.rint(np.asarray(array, np.float64) * 1000.0), 0, 65535).astype("<u2")
    raise ValueError(f"unknown image encoding {encoding!r}")
