"""Write a bag with `rosbags`' writers, atomically: a ROS 1 `.bag`, one rosbag2 `.mcap` or `.db3` file,
or a rosbag2 folder (`metadata.yaml` beside one file) in MCAP or sqlite3 storage.

Everything is written into a hidden folder next to the destination and moved into place once the bag
is complete; on an error nothing appears under the destination's name.
"""

import os
import shutil
from pathlib import Path

from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin, Writer as Ros2Writer

from rvt2cli.atomic import temp_path_for
from rvt2cli.rosbag.messages import Messages

STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
ROS2_FILE_STORAGE = {".mcap": "mcap", ".db3": "sqlite3"}


class BagWriter:
    """`with BagWriter(out, distro) as bag: bag.write(topic, datatype, message, t_ns)`.

    `out` ending in `.bag` is a ROS 1 bag (distro noetic); in `.mcap` or `.db3` one rosbag2 file;
    anything else a rosbag2 folder stored as `storage` (mcap or sqlite3)."""

    def __init__(self, out: str | Path, distro: str, storage: str = "mcap"):
        self.out = Path(out)
        self.messages = Messages(distro)
        self.staging = temp_path_for(self.out)
        if self.out.suffix == ".bag":
            if not self.messages.ros1:
                raise ValueError(f"a ROS 1 .bag needs the noetic messages, not {distro}")
            self.writer = Ros1Writer(self.staging / self.out.name)
        else:
            if self.messages.ros1:
                raise ValueError(f"{self.out}: ROS 1 messages go into a .bag file")
            storage = ROS2_FILE_STORAGE.get(self.out.suffix, storage)
            self.writer = Ros2Writer(self.staging / self.out.stem, version=8, storage_plugin=STORAGES[storage])
        self.connections = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> "BagWriter":
        self.staging.mkdir(parents=True)
        self.writer.open()
        return self

    def write(self, topic: str, datatype: str, msg, t_ns: int) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, datatype, typestore=self.messages.store)
        self.writer.write(self.connections[topic], int(t_ns), self.messages.serialize(msg, datatype))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def __exit__(self, exc_type, exc, tb):
        try:
            if exc_type is None:
                self.writer.close()
                os.replace(self._written(), self.out)
        finally:
            shutil.rmtree(self.staging, ignore_errors=True)
        return False

    def _written(self) -> Path:
        if self.out.suffix == ".bag":
            return self.staging / self.out.name
        folder = self.staging / self.out.stem
        if self.out.suffix in ROS2_FILE_STORAGE:
            return folder / f"{self.out.stem}{self.out.suffix}"
        return folder
