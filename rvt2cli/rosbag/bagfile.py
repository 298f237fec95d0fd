"""Open a robot's recording and read its messages, without ROS: a ROS 1 `.bag`, or a rosbag2 bag in
sqlite3 (`.db3`, ROS 2 Humble's default) or MCAP storage, given as the folder `ros2 bag record` writes
(`metadata.yaml` beside its files) or as one `.db3` / `.mcap` file.

`rosbags` reads all of them and decodes the messages with the definitions stored in the bag; a Humble
bag stores none, and is decoded with Humble's standard messages. Messages are streamed one at a time,
so a bag larger than the memory can be read. Every problem with the file itself is one `UserError`
naming it.
"""

import functools
import struct
from dataclasses import dataclass, field
from pathlib import Path

import apsw
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_typestore

from rvt2cli.errors import UserError

ROS2_FILES = {".mcap": "mcap", ".db3": "sqlite3"}
ROS2_STORAGES = ("mcap", "sqlite3")
BAG_KINDS = "a ROS 1 .bag file, or a ROS 2 bag: the folder `ros2 bag record` writes (with metadata.yaml) or one .db3 or .mcap file"
READ_ERRORS = (AnyReaderError, Ros1ReaderError, Ros2ReaderError, SerdeError, TypesysError, apsw.Error, struct.error,
               ValueError, EOFError, KeyError, IndexError, AssertionError)


@dataclass
class Topic:
    name: str
    datatype: str             # ROS 2 style for both ROS versions, e.g. sensor_msgs/msg/Image
    count: int = 0


@dataclass
class Bag:
    path: Path                # as the user gave it: a file or a rosbag2 folder
    ros_version: int          # 1 or 2
    topics: dict[str, Topic] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def info_command(self) -> str:
        return "rosbag info" if self.ros_version == 1 else "ros2 bag info"

    def has(self, topic: str) -> bool:
        return topic in self.topics and self.topics[topic].count > 0

    def require(self, topic: str, datatype: str, what: str, hint: str) -> None:
        """One line if the bag lacks `topic` (listing the topics it has) or carries another type on it."""
        if not self.has(topic):
            listed = ", ".join(sorted(t for t in self.topics if self.topics[t].count)) or "none"
            raise UserError(f"{self.path}: no {what} on topic {topic} (the bag has: {listed}); {hint}")
        found = self.topics[topic]
        if found.datatype != datatype:
            raise UserError(f"{self.path}: topic {topic} carries {found.datatype}, but the {what} must be a {datatype}; {hint}")

    def messages(self, topics):
        """(topic, decoded message, log time in ns) for the given topics, streamed in log-time order."""
        try:
            with _reader(self.path) as reader:
                topics = set(topics)
                wanted = [c for c in reader.connections if c.topic in topics]
                if not wanted:
                    return
                for connection, log_time, raw in reader.messages(connections=wanted):
                    yield connection.topic, reader.deserialize(raw, connection.msgtype), log_time
        except READ_ERRORS as e:
            raise _unreadable(self, "read the bag's messages", e) from None


def open_bag(path: str | Path) -> Bag:
    """Check that `path` is a bag rvt2 reads, with at least one message, and list its topics."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file or folder")
    ros_version = _ros_version(path)
    bag = Bag(path=path, ros_version=ros_version)
    try:
        with _reader(path) as reader:
            for name, info in reader.topics.items():
                bag.topics[name] = Topic(name, info.msgtype or "", info.msgcount)
    except READ_ERRORS as e:
        raise _unreadable(bag, "open the bag", e) from None
    if sum(t.count for t in bag.topics.values()) == 0:
        raise UserError(f"{path}: the bag has no messages; record the demonstration again")
    return bag


def _ros_version(path: Path) -> int:
    """1 or 2 from the path alone; one line for anything that is no bag rvt2 reads."""
    if path.is_dir():
        _check_rosbag2_folder(path)
        return 2
    if path.suffix == ".bag":
        return 1
    if path.suffix in ROS2_FILES:
        return 2
    raise UserError(f"{path}: unknown bag storage '{path.suffix or path.name}'; rvt2 reads {BAG_KINDS}")


def _check_rosbag2_folder(folder: Path) -> None:
    """The folder's metadata.yaml names a storage rvt2 reads (rosbags gives a terser reason otherwise)."""
    import yaml

    metadata_path = folder / "metadata.yaml"
    if not metadata_path.is_file():
        raise UserError(f"{folder}: a folder without metadata.yaml is not a rosbag2 bag; rvt2 reads {BAG_KINDS}")
    try:
        storage = yaml.safe_load(metadata_path.read_text())["rosbag2_bagfile_information"]["storage_identifier"]
    except (yaml.YAMLError, KeyError, TypeError, UnicodeDecodeError) as e:
        raise UserError(f"{metadata_path}: not a rosbag2 metadata.yaml ({type(e).__name__}); "
                        "check the bag with `ros2 bag info`") from None
    if storage not in ROS2_STORAGES:
        raise UserError(f"{folder}: unknown bag storage '{storage}'; rvt2 reads rosbag2 bags stored as "
                        f"{' or '.join(ROS2_STORAGES)}: record with `ros2 bag record -s mcap` (or -s sqlite3)")


@functools.cache
def _humble():
    return get_typestore(Stores.ROS2_HUMBLE)


def _reader(path: Path) -> AnyReader:
    # Bags that store no message definitions (ROS 2 Humble's) are decoded with Humble's standard messages.
    return AnyReader([path], default_typestore=_humble())


def _unreadable(bag: Bag, doing: str, error: Exception) -> UserError:
    """The one line for a bag `rosbags` cannot open or read, with the likely cause's fix."""
    reason = (" ".join(str(a) for a in error.args) or type(error).__name__).rstrip(".")
    if "Profile is not ros2" in reason:
        hint = "an MCAP file that is not a ROS 2 bag (an rvt2 episode?): give the bag the robot recorded"
    elif "end magic" in reason:
        hint = "a truncated MCAP file (was the recorder killed?): repair it with `ros2 bag reindex` or `mcap recover`"
    elif isinstance(error, apsw.Error) or "malformed" in reason or "missing tables" in reason:
        hint = "a damaged or truncated sqlite3 file (was the recorder killed?): copy the bag again, or record it again"
    else:
        hint = f"check it with `{bag.info_command}`, or record it again"
    return UserError(f"{bag.path}: cannot {doing} ({reason}); {hint}")
