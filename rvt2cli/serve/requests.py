"""A predict request, checked field by field into what the policy takes (`KeyframePolicy.inputs`).

Whatever a request holds, it is either turned into the policy's input or refused with a `WireError` naming
the field (`frames.front.depth`, `instruction`, ...) and what it must be. The wire format itself (msgpack,
arrays) is `rvt2_client.wire`'s.
"""

import math

import numpy as np

from rvt2_client.wire import WireError, array
from rvt2cli.data.episode import CameraFrame, Cloud
from rvt2cli.deploy import KeyframePolicy, PolicyInput
from rvt2cli.errors import UserError

MAX_INSTRUCTION_CHARS = 500   # an instruction is a sentence; the text encoder reads at most 256 tokens of it
MAX_CAMERAS = 16
MAX_CLOUD_POINTS = 4_000_000
PREDICT_FIELDS = ("type", "id", "token", "frames", "cloud", "instruction", "gripper_open", "finger_positions",
                  "keyframes_done", "task", "scene_bounds", "opencv_intrinsics")
CAMERA_FIELDS = ("rgb", "depth", "intrinsic", "cam2world")
DEPTH_DTYPES = ("uint16", "float32", "float64")


def predict_inputs(message: dict, policy: KeyframePolicy, cameras: tuple[str, ...] = ()) -> PolicyInput:
    """The policy's input for a predict request; `cameras`: the camera names every request must carry."""
    unknown = [key for key in message if key not in PREDICT_FIELDS]
    if unknown:
        raise WireError(str(unknown[0]), f"unknown field; a predict request holds {', '.join(PREDICT_FIELDS)}")
    instruction = _instruction(message.get("instruction"))
    gripper_open = _flag(message.get("gripper_open"), "gripper_open")
    fingers = _numbers(message.get("finger_positions", [0.04, 0.04]), 2, "finger_positions")
    keyframes_done = _count(message.get("keyframes_done", 0), "keyframes_done")
    opencv = _flag(message.get("opencv_intrinsics", True), "opencv_intrinsics")
    task, bounds = message.get("task"), message.get("scene_bounds")
    if task is not None and not isinstance(task, str):
        raise WireError("task", f"not a task name (got {type(task).__name__})")
    if bounds is not None:
        bounds = _numbers(bounds, 6, "scene_bounds")
        if not all(lo < hi for lo, hi in zip(bounds[:3], bounds[3:])):
            raise WireError("scene_bounds", f"{bounds} is not xmin ymin zmin xmax ymax zmax with each min below its max")
    elif policy.default_task(task) not in policy.tasks:
        what = f"unknown task {task!r}" if task is not None else "no task given"
        raise WireError("task", f"{what}: this policy knows {', '.join(policy.tasks)}; or give scene_bounds")
    if ("frames" in message) == ("cloud" in message):
        raise WireError("frames", "send either frames (the cameras' images) or cloud (a fused point cloud), one of them")
    state = (instruction, gripper_open, fingers, keyframes_done, task, bounds)
    if "cloud" in message:
        return policy.cloud_inputs(_cloud(message["cloud"]), *state)
    frames = _frames(message["frames"], cameras)
    try:
        return policy.inputs(frames, *state, opencv_intrinsics=opencv)
    except UserError as e:  # no point of the cameras lies inside the scene bounds
        raise WireError("frames", str(e)) from None


def _instruction(value) -> str:
    if not isinstance(value, str) or not value.strip():
        raise WireError("instruction", "missing or empty; send the task's instruction as text")
    if len(value) > MAX_INSTRUCTION_CHARS:
        raise WireError("instruction", f"{len(value)} characters, over the limit of {MAX_INSTRUCTION_CHARS}")
    return value


def _flag(value, field: str) -> bool:
    if not isinstance(value, bool):
        raise WireError(field, f"not true or false (got {value!r:.40})")
    return value


def _count(value, field: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < 2**31:
        raise WireError(field, f"not a whole number from 0 (got {value!r:.40})")
    return value


def _numbers(value, count: int, field: str) -> list[float]:
    """`count` finite numbers, from a list or an array."""
    if isinstance(value, dict):
        value = array(value, field).reshape(-1).tolist()
    if (not isinstance(value, (list, tuple)) or len(value) != count
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise WireError(field, f"not {count} numbers (got {value!r:.60})")
    if not all(math.isfinite(v) for v in value):
        raise WireError(field, f"{list(value)} holds a NaN or an infinity")
    return [float(v) for v in value]


def _matrix(value, shape: tuple[int, ...], field: str) -> np.ndarray:
    """A small finite float array of this shape, from an array (its dtype kept: a float32 pose fuses as it
    does in-process) or nested lists."""
    if isinstance(value, dict):
        out = array(value, field)
        if out.dtype.kind != "f":
            raise WireError(field, f"dtype {out.dtype.name}; send float32 or float64")
    else:
        try:
            out = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise WireError(field, f"not numbers (got {value!r:.60})") from None
    if out.shape != shape:
        raise WireError(field, f"shape {list(out.shape)}, not {list(shape)}")
    if not np.isfinite(out).all():
        raise WireError(field, "holds a NaN or an infinity")
    return out


def _image(value, field: str, dtypes: tuple[str, ...]) -> np.ndarray:
    out = array(value, field)
    if out.dtype.name not in dtypes:
        raise WireError(field, f"dtype {out.dtype.name}, not {' or '.join(dtypes)}")
    return out


def _frames(value, cameras: tuple[str, ...]) -> dict[str, CameraFrame]:
    if not isinstance(value, dict) or not value:
        raise WireError("frames", "no camera; send {name: {rgb, depth, intrinsic, cam2world}} for each camera")
    if len(value) > MAX_CAMERAS:
        raise WireError("frames", f"{len(value)} cameras, over the limit of {MAX_CAMERAS}")
    missing = [name for name in cameras if name not in value]
    if missing:
        raise WireError("frames", f"camera {missing[0]!r} missing; this server expects {', '.join(cameras)} (rvt2 serve --cameras)")
    frames = {}
    for name, camera in value.items():
        where = f"frames.{name}"
        if not isinstance(camera, dict):
            raise WireError(where, f"not a map of {', '.join(CAMERA_FIELDS)}")
        for key in camera:
            if key not in CAMERA_FIELDS:
                raise WireError(f"{where}.{key}", f"unknown field; a camera holds {', '.join(CAMERA_FIELDS)}")
        for key in CAMERA_FIELDS:
            if key not in camera:
                raise WireError(f"{where}.{key}", "missing")
        rgb = _image(camera["rgb"], f"{where}.rgb", ("uint8",))
        if rgb.ndim != 3 or rgb.shape[2] != 3 or 0 in rgb.shape:
            raise WireError(f"{where}.rgb", f"shape {list(rgb.shape)}, not [H, W, 3]")
        depth = _image(camera["depth"], f"{where}.depth", DEPTH_DTYPES)
        if depth.shape != rgb.shape[:2]:
            raise WireError(f"{where}.depth", f"shape {list(depth.shape)}, not the colour image's {list(rgb.shape[:2])}; "
                                              "send depth registered to the colour image")
        if depth.dtype.kind == "f":
            bad = int(np.count_nonzero(~np.isfinite(depth)))
            if bad:
                raise WireError(f"{where}.depth", f"{bad} NaN or infinite values; send 0 where there is no depth return")
            negative = int(np.count_nonzero(depth < 0))
            if negative:
                raise WireError(f"{where}.depth", f"{negative} negative values; depth is metres along the optical axis, "
                                                  "0 where there is no return")
        intrinsic = _matrix(camera["intrinsic"], (3, 3), f"{where}.intrinsic")
        if not (intrinsic[0, 0] > 0 and intrinsic[1, 1] > 0):
            raise WireError(f"{where}.intrinsic", f"focal lengths {intrinsic[0, 0]:g}, {intrinsic[1, 1]:g} are not positive")
        pose = _matrix(camera["cam2world"], (7,), f"{where}.cam2world")
        if not abs(np.linalg.norm(pose[3:]) - 1.0) < 1e-3:
            raise WireError(f"{where}.cam2world", f"quaternion {pose[3:].tolist()} is not of unit length "
                                                  "(x y z qx qy qz qw, the camera's pose in the base frame)")
        frames[str(name)] = CameraFrame(rgb=rgb, depth=depth, intrinsic=intrinsic, cam2world=pose)
    return frames


def _cloud(value) -> Cloud:
    if not isinstance(value, dict) or set(value) != {"xyz", "rgb"}:
        raise WireError("cloud", "not a map of xyz (float32 [N, 3], metres) and rgb (uint8 [N, 3])")
    xyz, rgb = array(value["xyz"], "cloud.xyz"), array(value["rgb"], "cloud.rgb")
    if xyz.dtype.name not in ("float32", "float64") or xyz.ndim != 2 or xyz.shape[1] != 3 or not 0 < len(xyz) <= MAX_CLOUD_POINTS:
        raise WireError("cloud.xyz", f"{xyz.dtype.name} {list(xyz.shape)}, not float32 [N, 3] with 1 to {MAX_CLOUD_POINTS} points")
    if rgb.dtype.name != "uint8" or rgb.shape != xyz.shape:
        raise WireError("cloud.rgb", f"{rgb.dtype.name} {list(rgb.shape)}, not uint8 {list(xyz.shape)}")
    if not np.isfinite(xyz).all():
        raise WireError("cloud.xyz", "holds a NaN or an infinity")
    return Cloud(xyz=xyz.copy(), rgb=rgb.copy())  # writable: the message's bytes are not
