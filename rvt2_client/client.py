"""`PolicyClient`: a robot program's handle on a policy served by `rvt2 serve`.

Synchronous (one request at a time per client; a program with several threads gives each its own), with
numpy, msgpack and websockets alone: no torch, no rvt2, no simulator. It keeps one websocket connection
open and opens it again, once, if the server closed it between two requests (a restart).
"""

from dataclasses import dataclass
from typing import Mapping

import numpy as np
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI
from websockets.sync.client import connect

from rvt2_client.wire import DEFAULT_PORT, pack, unpack


@dataclass(frozen=True)
class Keyframe:
    """The next keyframe: the tool centre point's target pose in the frame the camera poses were given in
    (the robot's base), the gripper state to set there, and whether to plan into it without collision
    checking (the last centimetres of an insertion or a grasp)."""

    position: tuple[float, float, float]            # metres
    quaternion: tuple[float, float, float, float]   # x y z w
    gripper_open: bool
    ignore_collisions: bool

    @property
    def pose(self) -> np.ndarray:
        """[7]: x y z qx qy qz qw."""
        return np.array(self.position + self.quaternion)


class PolicyError(ValueError):
    """The server refused a request: `field` names what was wrong (e.g. "frames.front.depth", "token")."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field, self.message = field, message


def _camera(frame) -> dict:
    """One camera as the wire carries it, from an object with rgb/depth/intrinsic/cam2world attributes (such
    as rvt2's CameraFrame) or a mapping with those keys; arrays keep their dtype (the server checks them)."""
    get = frame.get if isinstance(frame, Mapping) else lambda key: getattr(frame, key, None)
    return {key: np.asarray(value) for key in ("rgb", "depth", "intrinsic", "cam2world")
            if (value := get(key)) is not None}


class PolicyClient:
    """`PolicyClient("ws://gpu-box:8765", token=...).predict(frames, instruction, gripper_open, ...)` answers
    what `rvt2cli.deploy.KeyframePolicy.predict` answers on the same inputs, computed by the server.

    `timeout`: seconds to wait for an answer (the first request of a new instruction embeds it, and the
    first of all warms the model up: allow a few seconds). Raises `PolicyError` when the server refuses a
    request, `ConnectionError` when it cannot be reached, `TimeoutError` when it does not answer in time."""

    def __init__(self, url: str = f"ws://127.0.0.1:{DEFAULT_PORT}", token: str | None = None, timeout: float = 60.0,
                 connect_timeout: float = 10.0):
        self.url, self.token, self.timeout, self.connect_timeout = url, token, timeout, connect_timeout
        self._connection = None
        self._next_id = 0
        self._info: dict | None = None

    # --- the policy -------------------------------------------------------------------------------------
    def predict(self, frames: Mapping, instruction: str, gripper_open: bool, finger_positions=(0.04, 0.04),
                keyframes_done: int = 0, task: str | None = None, scene_bounds=None,
                opencv_intrinsics: bool = True) -> Keyframe:
        """The next keyframe from the cameras' frames: {name: frame}, each with `rgb` (uint8 [H, W, 3]), `depth`
        (uint16 millimetres or float32 metres [H, W], registered to the colour image, 0 where there is no
        return), `intrinsic` (K [3, 3], OpenCV's convention unless opencv_intrinsics=False) and `cam2world`
        (x y z qx qy qz qw in the robot's base frame, OpenCV optical axes)."""
        return self._predict({"frames": {str(name): _camera(frame) for name, frame in frames.items()}}, instruction,
                             gripper_open, finger_positions, keyframes_done, task, scene_bounds,
                             opencv_intrinsics=bool(opencv_intrinsics))

    def predict_cloud(self, xyz, rgb, instruction: str, gripper_open: bool, finger_positions=(0.04, 0.04),
                      keyframes_done: int = 0, task: str | None = None, scene_bounds=None) -> Keyframe:
        """The next keyframe from a cloud fused by the caller: xyz float32 [N, 3] (metres, base frame, cropped
        to the task's scene bounds) and rgb uint8 [N, 3]."""
        return self._predict({"cloud": {"xyz": np.asarray(xyz), "rgb": np.asarray(rgb)}}, instruction, gripper_open,
                             finger_positions, keyframes_done, task, scene_bounds)

    def info(self) -> dict:
        """The server's description: model, checkpoint sha256, config, device, tasks and their scene bounds,
        limits (the same document as GET /healthz)."""
        if self._info is None:
            self._info = self._call({"type": "info"})["info"]
        return self._info

    def _predict(self, observation: dict, instruction, gripper_open, finger_positions, keyframes_done, task,
                 scene_bounds, **extra) -> Keyframe:
        self.info()  # once per client: the server's limits, checked before a request is sent
        message = {"type": "predict", **observation, "instruction": instruction, "gripper_open": gripper_open,
                   "finger_positions": [float(v) for v in finger_positions], "keyframes_done": keyframes_done,
                   "task": task, "scene_bounds": None if scene_bounds is None else [float(v) for v in scene_bounds],
                   **extra}
        keyframe = self._call(message)["keyframe"]
        pose = [float(v) for v in keyframe["tcp_pose"]]
        return Keyframe(tuple(pose[:3]), tuple(pose[3:]), bool(keyframe["gripper_open"]), bool(keyframe["ignore_collisions"]))

    # --- the connection ---------------------------------------------------------------------------------
    def _connect(self):
        try:
            return connect(self.url, open_timeout=self.connect_timeout, max_size=None, compression=None)
        except (OSError, InvalidHandshake, InvalidURI, TimeoutError) as e:
            raise ConnectionError(f"{self.url}: cannot connect ({type(e).__name__}: {e}); is `rvt2 serve` running "
                                  "there, and is the port open?") from None

    def _call(self, message: dict) -> dict:
        self._next_id += 1
        message = {**message, "id": self._next_id}
        if self.token is not None:
            message["token"] = self.token
        data = pack(message)
        limit = (self._info or {}).get("max_message_bytes")
        if limit and len(data) > limit and message["type"] == "predict":
            raise PolicyError("message", f"{len(data) / 2**20:.1f} MiB is over the server's limit of "
                                         f"{limit / 2**20:.1f} MiB; send smaller images or fewer cameras")
        for attempt in (1, 2):
            fresh = self._connection is None
            if fresh:
                self._connection = self._connect()
            try:
                self._connection.send(data)
                reply = unpack(self._connection.recv(timeout=self.timeout))
                break
            except ConnectionClosed as e:
                self._connection = None
                if fresh or attempt == 2:  # closed by the server while answering this request
                    reason = f" ({e.rcvd.reason})" if e.rcvd is not None and e.rcvd.reason else ""
                    raise ConnectionError(f"{self.url}: the server closed the connection{reason}") from None
            except TimeoutError:
                self.close()  # a late answer would be taken for the next request's
                raise TimeoutError(f"{self.url}: no answer in {self.timeout:g} s") from None
        if reply.get("id") not in (message["id"], None):
            self.close()
            raise ConnectionError(f"{self.url}: the answer to request {reply.get('id')} came for request {message['id']}")
        if not reply.get("ok"):
            raise PolicyError(str(reply.get("field")), str(reply.get("error")))
        return reply

    def close(self) -> None:
        if self._connection is not None:
            self._connection.close()
            self._connection = None

    def __enter__(self) -> "PolicyClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
