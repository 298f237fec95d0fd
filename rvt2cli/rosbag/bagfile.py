"""Open a ROS 2 bag recorded in MCAP (`ros2 bag record -s mcap`) and read its messages, without ROS.

A bag is given as one `.mcap` file or as the folder `ros2 bag record` writes (`metadata.yaml` next to
one or more `.mcap` files, read in the order metadata.yaml lists them). Messages are decoded from CDR
with the message definitions stored in the bag (`mcap-ros2-support`). Every problem with the file
itself is one `UserError` naming it.
"""

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from rvt2cli.errors import UserError

MCAP_MAGIC = b"\x89MCAP0\r\n"
RECORD_HINT = "record with `ros2 bag record -s mcap`"


@dataclass
class Topic:
    name: str
    datatype: str             # e.g. sensor_msgs/msg/Image
    message_encoding: str     # cdr for ROS 2
    schema_encoding: str      # ros2msg (or ros2idl) for ROS 2
    count: int = 0


@dataclass
class Bag:
    path: Path                # as the user gave it: a file or a rosbag2 folder
    files: list[Path]
    topics: dict[str, Topic] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.path.name

    def has(self, topic: str) -> bool:
        return topic in self.topics and self.topics[topic].count > 0

    def require(self, topic: str, datatype: str, what: str, hint: str) -> None:
        """One line if the bag lacks `topic` (listing the topics it has) or carries another type on it."""
        if not self.has(topic):
            listed = ", ".join(sorted(t for t in self.topics if self.topics[t].count)) or "none"
            raise UserError(f"{self.path}: no {what} on topic {topic} (the bag has: {listed}); {hint}")
        found = self.topics[topic]
        if (found.message_encoding, found.schema_encoding) != ("cdr", "ros2msg"):
            raise UserError(f"{self.path}: topic {topic} is encoded as {found.message_encoding} with a "
                            f"{found.schema_encoding or 'missing'} schema, not as CDR with a ros2msg schema; {RECORD_HINT}")
        if found.datatype != datatype:
            raise UserError(f"{self.path}: topic {topic} carries {found.datatype}, but the {what} must be a {datatype}; {hint}")

    def messages(self, topics: list[str]):
        """(topic, decoded message, log time in ns) for the given topics, file by file in log-time order."""
        for path in self.files:
            with open(path, "rb") as stream:
                reader = make_reader(stream, decoder_factories=[DecoderFactory()])
                try:
                    for _, channel, message, decoded in reader.iter_decoded_messages(topics=topics, log_time_order=True):
                        yield channel.topic, decoded, message.log_time
                except (McapError, ValueError, EOFError, KeyError, NotImplementedError) as e:
                    raise UserError(f"{path}: cannot decode the bag's messages ({type(e).__name__}: {e}); "
                                    "check the file with `ros2 bag info`") from None


def open_bag(path: str | Path) -> Bag:
    """Check that `path` is a ROS 2 bag in MCAP with at least one message, and list its topics."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file or folder")
    bag = Bag(path=path, files=_mcap_files(path))
    profiles = set()
    for file in bag.files:
        profile, topics = _read_topics(file)
        profiles.add(profile)
        for topic in topics:
            known = bag.topics.setdefault(topic.name, Topic(topic.name, topic.datatype, topic.message_encoding,
                                                            topic.schema_encoding))
            known.count += topic.count
    encodings = {t.message_encoding for t in bag.topics.values()}
    if "ros2" not in profiles and "cdr" not in encodings:
        raise UserError(f"{path}: not a ROS 2 bag (MCAP profile '{'/'.join(sorted(profiles))}', message encodings "
                        f"{', '.join(sorted(encodings)) or 'none'}; ROS 2 bags hold CDR messages); {RECORD_HINT}")
    if sum(t.count for t in bag.topics.values()) == 0:
        raise UserError(f"{path}: the bag has no messages; record the demonstration again")
    return bag


def _mcap_files(path: Path) -> list[Path]:
    if path.is_dir():
        return _rosbag2_folder_files(path)
    _check_mcap_file(path)
    return [path]


def _rosbag2_folder_files(folder: Path) -> list[Path]:
    import yaml

    metadata_path = folder / "metadata.yaml"
    if not metadata_path.is_file():
        raise UserError(f"{folder}: a folder without metadata.yaml is not a rosbag2 bag; give the folder "
                        "`ros2 bag record -o NAME` wrote, or one .mcap file")
    try:
        info = yaml.safe_load(metadata_path.read_text())["rosbag2_bagfile_information"]
        storage = info.get("storage_identifier", "")
        names = list(info.get("relative_file_paths") or [])
    except (yaml.YAMLError, KeyError, TypeError, AttributeError, UnicodeDecodeError) as e:
        raise UserError(f"{metadata_path}: not a rosbag2 metadata.yaml ({type(e).__name__}); "
                        "check the bag with `ros2 bag info`") from None
    if storage != "mcap":
        raise UserError(f"{folder}: the bag is stored as '{storage}', not MCAP; convert it with `ros2 bag convert` "
                        f"or {RECORD_HINT}")
    if not names:
        raise UserError(f"{metadata_path}: lists no bag files (relative_file_paths is empty)")
    files = [folder / name for name in names]
    for file in files:
        if not file.is_file():
            raise UserError(f"{file}: listed in {metadata_path.name} but missing; copy the whole bag folder")
        _check_mcap_file(file)
    return files


def _check_mcap_file(path: Path) -> None:
    with open(path, "rb") as f:
        head = f.read(len(MCAP_MAGIC))
        f.seek(0, 2)
        size = f.tell()
        f.seek(max(0, size - len(MCAP_MAGIC)))
        tail = f.read()
    if head != MCAP_MAGIC:
        raise UserError(f"{path}: not an MCAP file (it does not start with the MCAP magic bytes); {RECORD_HINT}")
    if size < 2 * len(MCAP_MAGIC) or tail != MCAP_MAGIC:
        raise UserError(f"{path}: truncated MCAP file (no footer: was the recorder killed?); "
                        "repair it with `ros2 bag reindex` or `mcap recover`")


def _read_topics(path: Path) -> tuple[str, list[Topic]]:
    """The file's MCAP profile and its topics with message counts (from the summary, or by reading
    the file through when it has none)."""
    try:
        with open(path, "rb") as stream:
            reader = make_reader(stream)
            profile = reader.get_header().profile
            summary = reader.get_summary()
            if summary is not None and summary.statistics is not None:
                counts = summary.statistics.channel_message_counts
                channels = summary.channels.values()
                schemas = summary.schemas
            else:
                channels, schemas, counts = {}, {}, Counter()
                for schema, channel, _ in reader.iter_messages(log_time_order=False):
                    channels[channel.id] = channel
                    if schema is not None:
                        schemas[schema.id] = schema
                    counts[channel.id] += 1
                channels = channels.values()
    except (McapError, ValueError, EOFError) as e:
        raise UserError(f"{path}: corrupt MCAP file ({type(e).__name__}: {e}); check it with `ros2 bag info`") from None
    topics = []
    for channel in channels:
        schema = schemas.get(channel.schema_id)
        topics.append(Topic(channel.topic, schema.name if schema else "", channel.message_encoding,
                            schema.encoding if schema else "", counts.get(channel.id, 0)))
    return profile, topics
