"""Write rvt2 episodes (one MCAP file per episode), atomically.

    with EpisodeWriter(path, control_hz=20) as w:
        w.write_instruction(...)
        for each frame: w.write_frame(...)
        for obs frames: w.write_observation(frame, cameras, cloud)
        w.write_keyframes(annotation)   # optional: `rvt2 extract-keyframes` can add or replace them later
        w.finish(meta)          # metadata + footer, then the file appears under its final name

Nothing appears under `path` until `finish()` returns; an exception (or a kill) leaves at most a
hidden temporary file.
"""

import errno
import json
import os
from pathlib import Path

from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema as register_protobuf_schema

from rvt2cli import __version__
from rvt2cli.atomic import AtomicFile, output_error
from rvt2cli.data import messages, schemas, topics
from rvt2cli.data.episode import CameraFrame, Cloud, EpisodeMeta
from rvt2cli.data.keyframes import KeyframeAnnotation

CHUNK_SIZE = 1 << 20


def to_json_bytes(obj) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode()


class McapChannels:
    """An MCAP writer that registers schemas and channels the first time a topic is used."""

    def __init__(self, stream):
        self.writer = Writer(stream, compression=CompressionType.ZSTD, chunk_size=CHUNK_SIZE)
        self.writer.start(profile="", library=f"rvt2 {__version__}")
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}

    def _json_schema_id(self, name: str) -> int:
        if name not in self._schema_ids:
            self._schema_ids[name] = self.writer.register_schema(
                name=name, encoding="jsonschema", data=schemas.schema_text(name).encode()
            )
        return self._schema_ids[name]

    def _protobuf_schema_id(self, message_class) -> int:
        name = message_class.DESCRIPTOR.full_name
        if name not in self._schema_ids:
            self._schema_ids[name] = register_protobuf_schema(self.writer, message_class)
        return self._schema_ids[name]

    def _channel_id(self, topic: str, schema_id: int, encoding: str) -> int:
        if topic not in self._channel_ids:
            self._channel_ids[topic] = self.writer.register_channel(
                topic=topic, message_encoding=encoding, schema_id=schema_id
            )
        return self._channel_ids[topic]

    def write_json(self, topic: str, schema_name: str, obj: dict, t_ns: int) -> None:
        channel = self._channel_id(topic, self._json_schema_id(schema_name), "json")
        self.writer.add_message(channel, log_time=t_ns, data=to_json_bytes(obj), publish_time=t_ns)

    def write_protobuf(self, topic: str, msg, t_ns: int) -> None:
        channel = self._channel_id(topic, self._protobuf_schema_id(type(msg)), "protobuf")
        self.writer.add_message(channel, log_time=t_ns, data=msg.SerializeToString(), publish_time=t_ns)

    def write_raw(self, topic: str, schema_name: str, schema_encoding: str, schema_data: bytes,
                  message_encoding: str, data: bytes, t_ns: int, publish_ns: int) -> None:
        """Copy a message from another file, with its schema as it was."""
        if schema_name not in self._schema_ids:
            self._schema_ids[schema_name] = self.writer.register_schema(schema_name, schema_encoding, schema_data)
        channel = self._channel_id(topic, self._schema_ids[schema_name], message_encoding)
        self.writer.add_message(channel, log_time=t_ns, data=data, publish_time=publish_ns)

    def write_keyframes(self, annotation: KeyframeAnnotation, where: str) -> None:
        """An episode's keyframes and training samples, on /annotations/keyframes (checked against its schema)."""
        keyframes = annotation.to_json()
        schemas.check(schemas.KEYFRAMES, keyframes, f"{where} keyframes")
        self.write_json(topics.KEYFRAMES, schemas.KEYFRAMES, keyframes, 0)

    def write_episode_metadata(self, meta: EpisodeMeta) -> None:
        obj = meta.to_json_obj()
        schemas.check(schemas.EPISODE, obj, "episode metadata")
        self.writer.add_metadata(
            topics.METADATA_NAME,
            {"format_version": schemas.FORMAT_VERSION, "episode": json.dumps(obj, separators=(",", ":"))},
        )

    def finish(self) -> None:
        self.writer.finish()


def frame_time_ns(frame: int, control_hz: float) -> int:
    return int(round(frame * 1e9 / control_hz))


class EpisodeWriter:
    def __init__(self, path: str | os.PathLike, control_hz: float):
        self.path = Path(path)
        self.control_hz = control_hz
        self._target = AtomicFile(self.path)
        try:
            self._file = open(self._target.tmp, "wb")
        except OSError as e:
            raise output_error(self.path, e) from None
        self._mcap = McapChannels(self._file)
        self._obs_frames: list[int] = []
        self._num_frames = 0

    def _t(self, frame: int) -> int:
        return frame_time_ns(frame, self.control_hz)

    def write_instruction(self, text: str, task: str, template_index: int, variation: dict,
                          variation_index: int = 0) -> None:
        obj = {"text": text, "task": task, "template_index": template_index, "variation": variation,
               "variation_index": variation_index}
        schemas.check(schemas.INSTRUCTION, obj, f"{self.path} {topics.INSTRUCTION}")
        self._mcap.write_json(topics.INSTRUCTION, schemas.INSTRUCTION, obj, self._t(0))

    def write_frame(self, frame: int, *, joint_names, joint_positions, joint_velocities, gripper_width: float,
                    gripper_command: float, action, contacts, tcp_pose, sim_state: dict | None = None,
                    near=None) -> None:
        t = self._t(frame)
        state = {
            "frame": frame,
            "joint_names": list(joint_names),
            "joint_positions": [float(v) for v in joint_positions],
            "joint_velocities": [float(v) for v in joint_velocities],
            "gripper_width": float(gripper_width),
            "gripper_command": float(gripper_command),
            "action": None if action is None else [float(v) for v in action],
            "contacts": sorted(contacts),
        }
        if near is not None:
            state["near"] = sorted(near)
        self._mcap.write_json(topics.ROBOT_STATE, schemas.ROBOT_STATE, state, t)
        self._mcap.write_protobuf(topics.TCP_POSE, messages.pose_in_frame(tcp_pose, t), t)
        self._mcap.write_protobuf(topics.TF, messages.frame_transform(messages.WORLD_FRAME, topics.TCP_FRAME, tcp_pose, t), t)
        if sim_state is not None:
            self._mcap.write_json(topics.SIM_STATE, schemas.SIM_STATE, {"frame": frame, **sim_state}, t)
        self._num_frames = max(self._num_frames, frame + 1)

    def write_observation(self, frame: int, cameras: dict[str, CameraFrame], cloud: Cloud | None = None) -> None:
        """The cameras' RGB-D images at `frame`; `cloud`, if given, is stored on /points/world for viewing."""
        t = self._t(frame)
        for name, cam in cameras.items():
            frame_id = topics.camera_frame_id(name)
            h, w = cam.depth.shape
            self._mcap.write_protobuf(topics.TF, messages.frame_transform(messages.WORLD_FRAME, frame_id, cam.cam2world, t), t)
            self._mcap.write_protobuf(topics.camera_calibration(name), messages.camera_calibration(cam.intrinsic, w, h, t, frame_id), t)
            self._mcap.write_protobuf(topics.camera_image(name), messages.rgb_image(cam.rgb, t, frame_id), t)
            self._mcap.write_protobuf(topics.camera_depth(name), messages.depth_image(cam.depth, t, frame_id), t)
        if cloud is not None:
            self._mcap.write_protobuf(topics.CLOUD, messages.point_cloud(cloud.xyz, cloud.rgb, t), t)
        self._obs_frames.append(frame)

    def write_keyframes(self, annotation: KeyframeAnnotation) -> None:
        self._mcap.write_keyframes(annotation, str(self.path))

    @property
    def obs_frames(self) -> list[int]:
        return sorted(self._obs_frames)

    @property
    def num_frames(self) -> int:
        return self._num_frames

    def finish(self, meta: EpisodeMeta) -> Path:
        """Write the metadata and footer, then move the file to its final name."""
        try:
            self._mcap.write_episode_metadata(meta)
            self._mcap.finish()
            self._file.close()
        except OSError as e:
            self.abort()
            raise output_error(self.path, e) from None
        except BaseException:
            self.abort()
            raise
        return self._target.commit()

    def abort(self) -> None:
        if not self._file.closed:
            self._file.close()
        self._target.discard()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None or not self._file.closed:
            self.abort()
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            raise output_error(self.path, exc) from None
        return False
