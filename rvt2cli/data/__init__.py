"""The rvt2 episode format: one MCAP file per episode (docs/FORMAT.md). Every command reads and writes
episodes through this package.

The names below are imported on first use, so that code which only needs `rvt2cli.data.paths` or
`rvt2cli.data.episode` (training from a sample cache on a GPU machine) runs without the MCAP,
protobuf-schema and JSON-schema libraries.
"""

import importlib

_EXPORTS = {
    "write_keyframes": "rvt2cli.data.annotate",
    "CameraFrame": "rvt2cli.data.episode",
    "Cloud": "rvt2cli.data.episode",
    "EpisodeMeta": "rvt2cli.data.episode",
    "RobotTrajectory": "rvt2cli.data.episode",
    "Episode": "rvt2cli.data.reader",
    "read_episode": "rvt2cli.data.reader",
    "FORMAT_VERSION": "rvt2cli.data.schemas",
    "EpisodeWriter": "rvt2cli.data.writer",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'rvt2cli.data' has no attribute {name!r}")
