"""Read rvt2 episodes, with one clear error for every kind of bad file.

    ep = read_episode("demos/insert_peg_000.mcap")
    ep.meta.task, ep.instruction, ep.robot.tcp_pose, ep.cloud(40), ep.cameras(40), ep.keyframes.keyframes

The whole file is read into memory (an episode is a few MB); images and clouds are decoded on demand.
"""

import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.records import Message

from rvt2cli.data import messages, schemas, topics
from rvt2cli.data.episode import CameraFrame, Cloud, EpisodeMeta, RobotTrajectory
from rvt2cli.data.keyframes import KeyframeAnnotation
from rvt2cli.data.fusion import fuse
from rvt2cli.errors import UserError

MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass
class RawMessage:
    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    log_time: int
    publish_time: int
    data: bytes


@dataclass
class Episode:
    path: Path
    format_version: str
    meta: EpisodeMeta
    instruction: dict
    robot: RobotTrajectory
    keyframes: KeyframeAnnotation | None   # None until `rvt2 extract-keyframes` has run
    channel_counts: dict[str, int]
    size_bytes: int
    _by_topic_frame: dict[tuple[str, int], bytes] = field(repr=False, default_factory=dict)
    _sim_states: dict[int, dict] = field(repr=False, default_factory=dict)
    _tf: dict[tuple[str, int], bytes] = field(repr=False, default_factory=dict)

    @property
    def num_frames(self) -> int:
        return len(self.robot)

    @property
    def variation_index(self) -> int:
        """Which of its task's variations the episode is (files of format 1.1 and older: 0, the only one)."""
        return int(self.instruction.get("variation_index", 0))

    @property
    def obs_frames(self) -> list[int]:
        return list(self.meta.obs_frames)

    def require_keyframes(self) -> KeyframeAnnotation:
        if self.keyframes is None:
            raise UserError(f"{self.path}: no keyframes; run `rvt2 extract-keyframes {self.path.parent}/` first")
        return self.keyframes

    def check_frame(self, frame: int) -> None:
        if not 0 <= frame < self.num_frames:
            raise UserError(f"{self.path}: frame {frame} is out of range; this episode has frames 0..{self.num_frames - 1}")

    def _obs_bytes(self, topic: str, frame: int) -> bytes:
        self.check_frame(frame)
        try:
            return self._by_topic_frame[(topic, frame)]
        except KeyError:
            raise UserError(
                f"{self.path}: frame {frame} has no observation; frames with observations: "
                f"{_ranges(self.obs_frames)}"
            ) from None

    def cloud(self, frame: int, cameras: tuple[str, ...] | None = None) -> Cloud:
        """The fused world-frame cloud the policy sees at `frame` (from the stored RGB-D images of every
        camera, or of the named ones)."""
        frames = self.cameras(frame)
        if cameras:
            frames = {name: frames[name] for name in cameras}
        return fuse(frames, self.meta.scene_bounds, self.meta.voxel_size)

    def stored_cloud(self, frame: int) -> Cloud:
        """The optional `/points/world` cloud written for viewing (`rvt2 record --store-clouds`)."""
        msg = PointCloud.FromString(self._obs_bytes(topics.CLOUD, frame))
        try:
            xyz, rgb = messages.cloud_from(msg)
        except messages.MessageFormatError as e:
            raise UserError(f"{self.path}: {topics.CLOUD} frame {frame}: {e}") from None
        return Cloud(xyz=xyz, rgb=rgb)

    def cameras(self, frame: int) -> dict[str, CameraFrame]:
        out = {}
        for name in self.meta.cameras:
            rgb = messages.image_from(RawImage.FromString(self._obs_bytes(topics.camera_image(name), frame)))
            depth = messages.image_from(RawImage.FromString(self._obs_bytes(topics.camera_depth(name), frame)))
            calib = CameraCalibration.FromString(self._obs_bytes(topics.camera_calibration(name), frame))
            pose = messages.transform_pose(FrameTransform.FromString(self._tf[(topics.camera_frame_id(name), frame)]))
            out[name] = CameraFrame(rgb=rgb, depth=depth, intrinsic=messages.intrinsic_from(calib), cam2world=pose)
        return out

    def sim_state(self, frame: int) -> dict:
        self.check_frame(frame)
        if frame not in self._sim_states:
            raise UserError(f"{self.path}: no simulator state stored for frame {frame}")
        state = dict(self._sim_states[frame])
        state.pop("frame")
        return state


def _ranges(frames: list[int]) -> str:
    if not frames:
        return "none"
    return ", ".join(str(f) for f in frames[:12]) + (", ..." if len(frames) > 12 else "")


def _check_readable(path: Path) -> bytes:
    if not path.exists():
        raise UserError(f"{path}: no such file")
    if path.is_dir():
        raise UserError(f"{path}: is a directory, not an episode file")
    data = path.read_bytes()
    if not data.startswith(MCAP_MAGIC):
        raise UserError(f"{path}: not an MCAP file (it does not start with the MCAP magic bytes)")
    if len(data) < 2 * len(MCAP_MAGIC) or not data.endswith(MCAP_MAGIC):
        n = count_recoverable_messages(data)
        raise UserError(
            f"{path}: truncated MCAP file (no footer; was the writer killed?): {n} complete messages are recoverable. "
            "Record the episode again"
        )
    return data


def count_recoverable_messages(data: bytes) -> int:
    """Count the complete messages a linear read gets through before the file breaks off."""
    count = 0
    try:
        for record in StreamReader(io.BytesIO(data), skip_magic=False).records:
            if isinstance(record, Message):
                count += 1
    except Exception:  # noqa: BLE001 - any decoding failure marks where the file breaks off
        pass
    return count


def iter_raw_messages(path: Path, data: bytes):
    """All messages of a complete MCAP file in log-time order, with their schema and channel."""
    try:
        reader = make_reader(io.BytesIO(data))
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            yield RawMessage(
                topic=channel.topic,
                schema_name=schema.name if schema else "",
                schema_encoding=schema.encoding if schema else "",
                schema_data=schema.data if schema else b"",
                message_encoding=channel.message_encoding,
                log_time=message.log_time,
                publish_time=message.publish_time,
                data=message.data,
            )
    except (McapError, ValueError, EOFError) as e:
        raise UserError(f"{path}: corrupt MCAP file ({type(e).__name__}: {e})") from None


def read_metadata(path: Path, data: bytes) -> tuple[str, dict]:
    try:
        reader = make_reader(io.BytesIO(data))
        records = {m.name: m.metadata for m in reader.iter_metadata()}
    except (McapError, ValueError, EOFError) as e:
        raise UserError(f"{path}: corrupt MCAP file ({type(e).__name__}: {e})") from None
    if topics.METADATA_NAME not in records:
        raise UserError(f"{path}: not an rvt2 episode (no '{topics.METADATA_NAME}' metadata); record episodes with `rvt2 record`")
    record = records[topics.METADATA_NAME]
    version = record.get("format_version", "")
    schemas.check_format_version(version, str(path))
    try:
        meta = json.loads(record["episode"])
    except (KeyError, json.JSONDecodeError):
        raise UserError(f"{path}: the '{topics.METADATA_NAME}' metadata record is damaged (no readable 'episode' JSON)") from None
    schemas.check(schemas.EPISODE, meta, f"{path} metadata")
    return version, meta


@dataclass
class EpisodeOverview:
    meta: EpisodeMeta
    topics: set[str]


def read_episode_overview(path: str | Path) -> EpisodeOverview:
    """Metadata and channel names only, from the file's summary (cheap; refuses bad files like
    read_episode does)."""
    path = Path(path)
    data = _check_readable(path)
    _, meta = read_metadata(path, data)
    try:
        summary = make_reader(io.BytesIO(data)).get_summary()
    except (McapError, ValueError, EOFError) as e:
        raise UserError(f"{path}: corrupt MCAP file ({type(e).__name__}: {e})") from None
    topics_ = {c.topic for c in summary.channels.values()} if summary else set()
    return EpisodeOverview(meta=EpisodeMeta(**meta), topics=topics_)


_JSON_TOPICS = {
    topics.ROBOT_STATE: schemas.ROBOT_STATE,
    topics.SIM_STATE: schemas.SIM_STATE,
    topics.INSTRUCTION: schemas.INSTRUCTION,
    topics.KEYFRAMES: schemas.KEYFRAMES,
}


def read_episode(path: str | Path) -> Episode:
    path = Path(path)
    data = _check_readable(path)
    version, meta_obj = read_metadata(path, data)
    meta = EpisodeMeta(**meta_obj)
    counts: dict[str, int] = {}
    states: list[dict] = []
    poses: list[np.ndarray] = []
    by_topic_frame: dict[tuple[str, int], bytes] = {}
    tf: dict[tuple[str, int], bytes] = {}
    sim_states: dict[int, dict] = {}
    instruction = None
    keyframes = None
    dt_ns = 1e9 / meta.control_hz

    for msg in iter_raw_messages(path, data):
        counts[msg.topic] = counts.get(msg.topic, 0) + 1
        frame = int(round(msg.log_time / dt_ns))
        where = f"{path} {msg.topic} frame {frame}"
        if msg.topic in _JSON_TOPICS:
            expected = _JSON_TOPICS[msg.topic]
            if msg.schema_name != expected:
                raise UserError(f"{where}: schema {msg.schema_name!r}, expected {expected!r}")
            try:
                obj = json.loads(msg.data)
            except json.JSONDecodeError as e:
                raise UserError(f"{where}: message is not valid JSON ({e})") from None
            schemas.check(expected, obj, where)
            if msg.topic == topics.ROBOT_STATE:
                states.append(obj)
            elif msg.topic == topics.SIM_STATE:
                sim_states[obj["frame"]] = obj
            elif msg.topic == topics.INSTRUCTION:
                instruction = obj
            else:
                keyframes = KeyframeAnnotation.from_json(obj)
        elif msg.topic == topics.TCP_POSE:
            poses.append(messages.pose_from(_parse(PoseInFrame, msg.data, where)))
        elif msg.topic == topics.TF:
            child = _parse(FrameTransform, msg.data, where).child_frame_id
            tf[(child, frame)] = msg.data
        else:
            by_topic_frame[(msg.topic, frame)] = msg.data

    if instruction is None or not states:
        raise UserError(f"{path}: not a complete rvt2 episode (no {topics.INSTRUCTION} or {topics.ROBOT_STATE} messages)")
    if len(poses) != len(states):
        raise UserError(f"{path}: {len(states)} robot states but {len(poses)} TCP poses; the file is damaged")
    robot = RobotTrajectory(
        joint_names=states[0]["joint_names"],
        joint_positions=np.array([s["joint_positions"] for s in states], dtype=np.float32),
        joint_velocities=np.array([s["joint_velocities"] for s in states], dtype=np.float32),
        gripper_width=np.array([s["gripper_width"] for s in states], dtype=np.float32),
        gripper_command=np.array([s["gripper_command"] for s in states], dtype=np.float32),
        tcp_pose=np.stack(poses),
        actions=[s["action"] for s in states],
        contacts=[s["contacts"] for s in states],
        near=[s["near"] for s in states] if all("near" in s for s in states) else None,
    )
    return Episode(
        path=path, format_version=version, meta=meta, instruction=instruction, robot=robot, keyframes=keyframes,
        channel_counts=counts, size_bytes=len(data), _by_topic_frame=by_topic_frame, _sim_states=sim_states, _tf=tf,
    )


def _parse(message_class, data: bytes, where: str):
    try:
        return message_class.FromString(data)
    except Exception as e:  # noqa: BLE001 - protobuf raises DecodeError or RuntimeError depending on backend
        raise UserError(f"{where}: message is not a valid {message_class.DESCRIPTOR.full_name} ({e})") from None
