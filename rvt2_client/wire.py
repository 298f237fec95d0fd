"""The wire format of `rvt2 serve`: msgpack messages over a websocket, numpy arrays as typed byte strings.

One message per websocket binary frame, a msgpack map. A numpy array travels as the map

    {"__ndarray__": True, "dtype": "uint16", "shape": [480, 640], "data": <bytes, little-endian, C order>}

with a dtype from `DTYPES` alone: plain numbers, never Python objects, so decoding a message runs no code
(msgpack-numpy, openpi's format, unpickles object arrays; this format has none). Anything that is not an
array is a msgpack string, number, boolean, nil, list or map.

Requests (client -> server), each with an `id` the reply repeats and, where the server was started with
`--token-file`, the shared `token`:

    {"type": "info", "id": 1, "token": "..."}
    {"type": "predict", "id": 2, "token": "...",
     "frames": {"front": {"rgb": uint8 [H, W, 3], "depth": uint16 mm or float32 m [H, W] (0: no return),
                          "intrinsic": [3, 3] OpenCV K, "cam2world": [7] x y z qx qy qz qw}, ...},
       (or "cloud": {"xyz": float32 [N, 3] m, base frame, "rgb": uint8 [N, 3]}, a cloud fused by the caller)
     "instruction": "put the block on the plate", "gripper_open": true, "finger_positions": [0.04, 0.04],
     "keyframes_done": 0, "task": "stack_blocks" (or nil), "scene_bounds": [6] (or nil), "opencv_intrinsics": true}

Replies (server -> client):

    {"id": 2, "ok": true, "keyframe": {"tcp_pose": [x, y, z, qx, qy, qz, qw], "gripper_open": true,
                                       "ignore_collisions": false}, "batch": 3, "server_ms": 41.2}
    {"id": 1, "ok": true, "info": {...}}                       (the same document as GET /healthz)
    {"id": 2, "ok": false, "field": "frames.front.depth", "error": "..."}

This module needs numpy and msgpack alone; the server and the client both use it.
"""

import math

import msgpack
import numpy as np

PROTOCOL = 1
NDARRAY = "__ndarray__"
DTYPES = ("bool", "uint8", "uint16", "int32", "int64", "float32", "float64")
HEALTH_PATH = "/healthz"
DEFAULT_PORT = 8765
MAX_MESSAGE_BYTES = 64 * 2**20   # the server's default limit on one request (`rvt2 serve --max-message-mb`)


class WireError(ValueError):
    """A value that is not what its field must be: `field` names it (e.g. "frames.front.depth")."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field, self.message = field, message


def _encode(value):
    if isinstance(value, np.ndarray):
        if value.dtype.name not in DTYPES:
            raise TypeError(f"an array of dtype {value.dtype} cannot be sent; convert it to one of {', '.join(DTYPES)}")
        little = value.astype(value.dtype.newbyteorder("<"), copy=False)
        return {NDARRAY: True, "dtype": value.dtype.name, "shape": list(value.shape),
                "data": np.ascontiguousarray(little).tobytes()}
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} cannot be sent (numbers, strings, lists, maps and numpy arrays can)")


def pack(message: dict) -> bytes:
    return msgpack.packb(message, default=_encode, use_bin_type=True)


def unpack(data: bytes) -> dict:
    """A message's map; its arrays stay maps until `array` reads them (and names the field if one is wrong).
    Raises ValueError for bytes that are not one msgpack map."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ValueError("a text frame; messages are msgpack maps in binary frames")
    try:
        message = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except Exception as e:  # noqa: BLE001 - msgpack raises several types for malformed input
        raise ValueError(f"not msgpack ({type(e).__name__})") from None
    if not isinstance(message, dict):
        raise ValueError(f"a msgpack {type(message).__name__}, not a map")
    return message


def array(value, field: str) -> np.ndarray:
    """The numpy array an encoded map holds (a read-only view of the message's bytes)."""
    if isinstance(value, np.ndarray):
        return value
    if not isinstance(value, dict) or value.get(NDARRAY) is not True:
        raise WireError(field, f"not an array (got {type(value).__name__}); send a numpy array")
    dtype, shape, data = value.get("dtype"), value.get("shape"), value.get("data")
    if dtype not in DTYPES:
        raise WireError(field, f"dtype {dtype!r} is not one of {', '.join(DTYPES)}")
    if (not isinstance(shape, list) or len(shape) > 8
            or not all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n for n in shape)):
        raise WireError(field, f"shape {shape!r} is not a list of at most 8 sizes")
    if not isinstance(data, bytes):
        raise WireError(field, "its data is not a byte string")
    itemsize = np.dtype(dtype).itemsize
    if len(data) != itemsize * math.prod(shape):
        raise WireError(field, f"{len(data)} bytes do not hold a {dtype} array of shape {shape}")
    return np.frombuffer(data, np.dtype(dtype).newbyteorder("<")).reshape(shape)
