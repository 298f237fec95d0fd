"""The rvt2 episode format: one MCAP file per episode (docs/FORMAT.md). Every command reads and writes
episodes through this package."""

from rvt2cli.data.annotate import write_keyframes
from rvt2cli.data.episode import CameraFrame, Cloud, EpisodeMeta, RobotTrajectory
from rvt2cli.data.reader import Episode, read_episode
from rvt2cli.data.schemas import FORMAT_VERSION
from rvt2cli.data.writer import EpisodeWriter

__all__ = [
    "CameraFrame", "Cloud", "Episode", "EpisodeMeta", "EpisodeWriter", "FORMAT_VERSION", "RobotTrajectory",
    "read_episode", "write_keyframes",
]
