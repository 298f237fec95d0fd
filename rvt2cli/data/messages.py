"""Conversions between numpy arrays and the Foxglove well-known messages we store.

Conventions used everywhere in rvt2:
- poses are 7 numbers `x y z qx qy qz qw` (metres; scalar-last quaternion, as scipy and Foxglove);
- clouds are `xyz` float32 [N, 3] (metres, world frame) and `rgb` uint8 [N, 3];
- colour images are uint8 [H, W, 3]; depth images float32 [H, W] in metres (0 = no return).
"""

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

WORLD_FRAME = "world"

# One point of a stored cloud: x y z as float32, then red green blue as uint8 (15 bytes).
CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
_CLOUD_FIELDS = [
    ("x", 0, PackedElementField.FLOAT32),
    ("y", 4, PackedElementField.FLOAT32),
    ("z", 8, PackedElementField.FLOAT32),
    ("red", 12, PackedElementField.UINT8),
    ("green", 13, PackedElementField.UINT8),
    ("blue", 14, PackedElementField.UINT8),
]


class MessageFormatError(ValueError):
    """A well-known message whose layout is not the one rvt2 writes."""


def _stamp(msg, t_ns: int) -> None:
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(int(t_ns), 1_000_000_000)


def _set_pose(pose_msg, pose7) -> None:
    x, y, z, qx, qy, qz, qw = (float(v) for v in pose7)
    pose_msg.position.x, pose_msg.position.y, pose_msg.position.z = x, y, z
    pose_msg.orientation.x, pose_msg.orientation.y = qx, qy
    pose_msg.orientation.z, pose_msg.orientation.w = qz, qw


def pose_in_frame(pose7, t_ns: int, frame_id: str = WORLD_FRAME) -> PoseInFrame:
    msg = PoseInFrame(frame_id=frame_id)
    _stamp(msg, t_ns)
    _set_pose(msg.pose, pose7)
    return msg


def pose_from(msg: PoseInFrame) -> np.ndarray:
    p, q = msg.pose.position, msg.pose.orientation
    return np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w], dtype=np.float64)


def frame_transform(parent: str, child: str, pose7, t_ns: int) -> FrameTransform:
    """Transform that maps points in `child` into `parent` (the child's pose in the parent)."""
    msg = FrameTransform(parent_frame_id=parent, child_frame_id=child)
    _stamp(msg, t_ns)
    x, y, z, qx, qy, qz, qw = (float(v) for v in pose7)
    msg.translation.x, msg.translation.y, msg.translation.z = x, y, z
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = qx, qy, qz, qw
    return msg


def transform_pose(msg: FrameTransform) -> np.ndarray:
    t, q = msg.translation, msg.rotation
    return np.array([t.x, t.y, t.z, q.x, q.y, q.z, q.w], dtype=np.float64)


def point_cloud(xyz: np.ndarray, rgb: np.ndarray, t_ns: int, frame_id: str = WORLD_FRAME) -> PointCloud:
    if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape:
        raise ValueError(f"cloud needs xyz [N,3] and rgb [N,3], got {xyz.shape} and {rgb.shape}")
    packed = np.empty(len(xyz), dtype=CLOUD_DTYPE)
    packed["x"], packed["y"], packed["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    packed["red"], packed["green"], packed["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    msg = PointCloud(frame_id=frame_id, point_stride=CLOUD_DTYPE.itemsize, data=packed.tobytes())
    _stamp(msg, t_ns)
    msg.pose.orientation.w = 1.0
    for name, offset, ftype in _CLOUD_FIELDS:
        msg.fields.add(name=name, offset=offset, type=ftype)
    return msg


def cloud_from(msg: PointCloud) -> tuple[np.ndarray, np.ndarray]:
    fields = [(f.name, f.offset, f.type) for f in msg.fields]
    if fields != _CLOUD_FIELDS or msg.point_stride != CLOUD_DTYPE.itemsize:
        raise MessageFormatError(f"point cloud layout {fields} (stride {msg.point_stride}) is not rvt2's xyz+rgb layout")
    packed = np.frombuffer(msg.data, dtype=CLOUD_DTYPE)
    xyz = np.stack([packed["x"], packed["y"], packed["z"]], axis=1)
    rgb = np.stack([packed["red"], packed["green"], packed["blue"]], axis=1)
    return xyz, rgb


def rgb_image(rgb: np.ndarray, t_ns: int, frame_id: str) -> RawImage:
    h, w, _ = rgb.shape
    msg = RawImage(frame_id=frame_id, width=w, height=h, encoding="rgb8", step=3 * w, data=np.ascontiguousarray(rgb, np.uint8).tobytes())
    _stamp(msg, t_ns)
    return msg


def depth_image(depth: np.ndarray, t_ns: int, frame_id: str) -> RawImage:
    h, w = depth.shape
    msg = RawImage(frame_id=frame_id, width=w, height=h, encoding="32FC1", step=4 * w, data=np.ascontiguousarray(depth, "<f4").tobytes())
    _stamp(msg, t_ns)
    return msg


def image_from(msg: RawImage) -> np.ndarray:
    if msg.encoding == "rgb8":
        return np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width, 3)
    if msg.encoding == "32FC1":
        return np.frombuffer(msg.data, "<f4").reshape(msg.height, msg.width)
    raise MessageFormatError(f"image encoding {msg.encoding!r} is not one rvt2 writes (rgb8, 32FC1)")


def camera_calibration(intrinsic: np.ndarray, width: int, height: int, t_ns: int, frame_id: str) -> CameraCalibration:
    """Pinhole calibration in OpenCV convention (no distortion)."""
    K = np.asarray(intrinsic, dtype=np.float64)
    P = np.zeros((3, 4))
    P[:, :3] = K
    msg = CameraCalibration(frame_id=frame_id, width=width, height=height, distortion_model="plumb_bob")
    _stamp(msg, t_ns)
    msg.D.extend([0.0] * 5)
    msg.K.extend(K.ravel().tolist())
    msg.R.extend(np.eye(3).ravel().tolist())
    msg.P.extend(P.ravel().tolist())
    return msg


def intrinsic_from(msg: CameraCalibration) -> np.ndarray:
    return np.array(msg.K, dtype=np.float64).reshape(3, 3)
