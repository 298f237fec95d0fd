"""sensor_msgs/Image and CameraInfo <-> numpy, for the encodings realsense-ros publishes.

Colour: `rgb8` or `bgr8`. Depth: `16UC1` (millimetres, as realsense-ros publishes it) or `32FC1`
(metres). A depth of 0 (or NaN, or inf) is no return. Rows may be padded (`step`) and multi-byte
pixels may be big-endian (`is_bigendian`), as the message allows.
"""

import numpy as np

from rvt2cli.data.fusion import depth_in_metres, intrinsic_from_opencv, intrinsic_to_opencv

COLOUR_ENCODINGS = ("rgb8", "bgr8")
DEPTH_ENCODINGS = ("16UC1", "32FC1")
_PIXEL = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "16UC1": (np.uint16, 1), "32FC1": (np.float32, 1)}


def stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def stamp(t_ns: int) -> dict:
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def layout_problem(msg) -> str | None:
    """Why the image's bytes do not hold `height` rows of `width` pixels of its encoding, or None."""
    dtype, channels = _PIXEL[msg.encoding]
    row = msg.width * channels * np.dtype(dtype).itemsize
    if msg.step < row or len(msg.data) < msg.step * msg.height:
        return f"{len(msg.data)} bytes with step {msg.step} cannot hold {msg.height} rows of {msg.width} {msg.encoding} pixels"
    return None


def _pixels(msg) -> np.ndarray:
    dtype, channels = _PIXEL[msg.encoding]
    dtype = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    rows = np.frombuffer(msg.data, np.uint8, count=msg.step * msg.height).reshape(msg.height, msg.step)
    row_bytes = msg.width * channels * dtype.itemsize
    pixels = np.ascontiguousarray(rows[:, :row_bytes]).view(dtype).reshape(msg.height, msg.width, channels)
    return pixels.astype(dtype.newbyteorder("="))


def colour_rgb(msg) -> np.ndarray:
    """uint8 [H, W, 3] in RGB order."""
    pixels = _pixels(msg)
    return np.ascontiguousarray(pixels[..., ::-1] if msg.encoding == "bgr8" else pixels)


def depth_metres(msg) -> np.ndarray:
    """float32 [H, W], metres along the optical axis, 0 = no return (16UC1 is millimetres, 32FC1 metres)."""
    return depth_in_metres(_pixels(msg)[..., 0])


def intrinsic(camera_info) -> np.ndarray:
    """rvt2's K [3, 3] of a camera described by a sensor_msgs/CameraInfo (pixel centres on integers)."""
    return intrinsic_from_opencv(camera_info.k)


# --- writing -----------------------------------------------------------------------------------------

def image_message(array: np.ndarray, encoding: str, t_ns: int, frame_id: str) -> dict:
    """A sensor_msgs/Image (as the dict mcap_ros2's writer takes) from an RGB uint8 [H, W, 3] image
    (`rgb8`, `bgr8`) or a float depth [H, W] in metres (`32FC1`, `16UC1` in millimetres)."""
    if encoding == "rgb8":
        pixels = np.asarray(array, np.uint8)
    elif encoding == "bgr8":
        pixels = np.asarray(array, np.uint8)[..., ::-1]
    elif encoding == "32FC1":
        pixels = np.asarray(array, "<f4")
    elif encoding == "16UC1":
        pixels = np.clip(np.rint(np.asarray(array, np.float64) * 1000.0), 0, 65535).astype("<u2")
    else:
        raise ValueError(f"unknown image encoding {encoding!r}")
    height, width = pixels.shape[:2]
    data = np.ascontiguousarray(pixels).tobytes()
    return {"header": {"stamp": stamp(t_ns), "frame_id": frame_id}, "height": height, "width": width,
            "encoding": encoding, "is_bigendian": 0, "step": len(data) // height, "data": data}


def camera_info_message(K: np.ndarray, width: int, height: int, t_ns: int, frame_id: str) -> dict:
    """A sensor_msgs/CameraInfo of a pinhole camera without distortion, from rvt2's K."""
    K = intrinsic_to_opencv(K)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return {"header": {"stamp": stamp(t_ns), "frame_id": frame_id}, "height": height, "width": width,
            "distortion_model": "plumb_bob", "d": [0.0] * 5, "k": K.ravel().tolist(), "r": np.eye(3).ravel().tolist(),
            "p": P.ravel().tolist(), "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}
