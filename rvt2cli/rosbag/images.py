"""sensor_msgs/Image and CompressedImage -> numpy, for the encodings camera drivers publish.

Raw colour: `rgb8` or `bgr8` (or with alpha, `rgba8`, `bgra8`: Azure Kinect's, dropped). Raw depth: `16UC1` (millimetres, as realsense-ros publishes it) or
`32FC1` (metres). Rows may be padded (`step`) and multi-byte pixels may be big-endian
(`is_bigendian`), as the message allows. A depth of 0 (or NaN, or inf) is no return.

Compressed colour (image_transport's `compressed`): a JPEG or PNG, decoded by OpenCV. Compressed depth
(`compressedDepth`): a 12-byte header (int32 format, two float32 quantisation parameters) and a PNG;
for `16UC1` the PNG holds the millimetres themselves, for `32FC1` inverse depth, quantised
(depth = a / (value - b)). OpenCV decodes them directly rather than through `rosbags-image`, whose
decoder asserts on a damaged image instead of saying so.
"""

import struct

import cv2
import numpy as np

from rvt2cli.data.fusion import depth_in_metres

COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
DEPTH_ENCODINGS = ("16UC1", "32FC1")
COMPRESSED_COLOUR = ("jpeg", "png")
COMPRESSED_DEPTH = "compressedDepth"
_PIXEL = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
          "16UC1": (np.uint16, 1), "32FC1": (np.float32, 1)}
DEPTH_HEADER = struct.Struct("<iff")   # compressed_depth_image_transport's ConfigHeader


class ImageProblem(ValueError):
    """Why an image cannot be read (the caller names the bag and the topic)."""


def stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def is_compressed(msg) -> bool:
    return hasattr(msg, "format")


# --- raw images -----------------------------------------------------------------------------------

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


# --- compressed images ----------------------------------------------------------------------------

def compressed_encoding(msg) -> str:
    """The original encoding a CompressedImage's `format` names ('rgb8; jpeg compressed bgr8' -> rgb8),
    or '' where it names none (older drivers write just 'jpeg')."""
    head = msg.format.split(";", 1)[0].strip()
    return head if ";" in msg.format else ""


def format_problem(msg, depth: bool) -> str | None:
    """Why rvt2 cannot read a CompressedImage of this `format`, or None."""
    fmt = msg.format.lower()
    if depth:
        if COMPRESSED_DEPTH.lower() not in fmt or compressed_encoding(msg) not in DEPTH_ENCODINGS:
            return f"compressed depth of format '{msg.format}'; rvt2 reads compressedDepth of 16UC1 or 32FC1 (PNG)"
        if "rvl" in fmt:
            return f"compressed depth of format '{msg.format}'; rvt2 reads compressedDepth as PNG, not RVL"
        return None
    if not any(kind in fmt for kind in COMPRESSED_COLOUR) or compressed_encoding(msg) not in ("", *COLOUR_ENCODINGS):
        return f"compressed colour of format '{msg.format}'; rvt2 reads JPEG or PNG of rgb8 or bgr8 images"
    return None


def _decode(data, flags: int) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if len(data) else None
    if image is None:
        raise ImageProblem("the compressed image cannot be decoded")
    return image


# --- both -----------------------------------------------------------------------------------------

def colour_rgb(msg) -> np.ndarray:
    """uint8 [H, W, 3] in RGB order, from an Image or a CompressedImage."""
    if is_compressed(msg):
        return np.ascontiguousarray(_decode(msg.data, cv2.IMREAD_COLOR)[..., ::-1])   # OpenCV decodes to BGR
    pixels = _pixels(msg)[..., :3]
    return np.ascontiguousarray(pixels[..., ::-1] if msg.encoding.startswith("bgr") else pixels)


def depth_metres(msg) -> np.ndarray:
    """float32 [H, W], metres along the optical axis, 0 = no return, from an Image or a compressedDepth."""
    if not is_compressed(msg):
        return depth_in_metres(_pixels(msg)[..., 0])
    if len(msg.data) <= DEPTH_HEADER.size:
        raise ImageProblem(f"{len(msg.data)} bytes cannot hold a compressedDepth header and image")
    _, quant_a, quant_b = DEPTH_HEADER.unpack_from(bytes(msg.data[:DEPTH_HEADER.size]))
    values = _decode(msg.data[DEPTH_HEADER.size:], cv2.IMREAD_UNCHANGED)
    if values.ndim != 2 or values.dtype != np.uint16:
        raise ImageProblem(f"its PNG holds {values.dtype} pixels in {values.shape[2] if values.ndim == 3 else 1} channels, "
                           "not 16-bit depth")
    if compressed_encoding(msg) == "16UC1":
        return depth_in_metres(values)
    quantised = values.astype(np.float32)
    with np.errstate(divide="ignore"):
        metres = np.where(values > 0, np.float32(quant_a) / (quantised - np.float32(quant_b)), np.float32(0.0))
    return depth_in_metres(metres)


def image_size(msg, depth: bool) -> tuple[int, int]:
    """(width, height): from the header of an Image, by decoding a CompressedImage."""
    if not is_compressed(msg):
        return msg.width, msg.height
    pixels = depth_metres(msg) if depth else colour_rgb(msg)
    return pixels.shape[1], pixels.shape[0]
