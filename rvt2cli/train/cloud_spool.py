"""Clouds from the processes that read episodes to the one that trains, through a temporary file each.

A reader process returns its episode's samples through the pool's result pipe, and one process receives and
unpickles every episode's: rvt2-18's clouds are about 28 MB an episode, 44.5 GiB in all, and that one
process, not the readers, then sets the pace (docs/BENCHMARKS.md, "Reading episodes"). Instead each reader
writes its episode's clouds, concatenated, into one file of a private temporary folder (in /dev/shm where it
has room: memory, not disk) and returns only the file's name and the clouds' lengths; the receiving process
reads several such files at once, in threads, takes each sample's cloud as a view of its episode's array and
deletes the file. A write that fails (a full folder) sends that episode's clouds through the pipe instead.
"""

import contextlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

SHM = Path("/dev/shm")
SHM_ROOM = 4 << 30   # /dev/shm only with this much free: a container's default 64 MB would not hold a few episodes


@dataclass(frozen=True)
class SpooledClouds:
    path: str            # xyz float32 [P, 3], then rgb uint8 [P, 3]: P, the points of all the episode's samples
    lengths: tuple[int, ...]


@contextlib.contextmanager
def spool_folder():
    """A private temporary folder for the clouds in flight, removed afterwards, whatever happened."""
    memory = SHM.is_dir() and os.access(SHM, os.W_OK) and shutil.disk_usage(SHM).free >= SHM_ROOM
    folder = tempfile.mkdtemp(prefix="rvt2-clouds-", dir=SHM if memory else None)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def spool_clouds(xyz: list[np.ndarray], rgb: list[np.ndarray], folder: str) -> SpooledClouds | None:
    """One episode's clouds into a new file of `folder`; None where that fails (the caller sends them itself)."""
    try:
        fd, path = tempfile.mkstemp(dir=folder, suffix=".clouds")
    except OSError:
        return None
    try:
        with os.fdopen(fd, "wb") as f:
            for arrays, dtype in ((xyz, np.float32), (rgb, np.uint8)):
                for array in arrays:
                    f.write(np.ascontiguousarray(array, dtype=dtype).data)
    except OSError:
        with contextlib.suppress(OSError):
            os.unlink(path)
        return None
    return SpooledClouds(path, tuple(len(a) for a in xyz))


def unspool_clouds(spooled: SpooledClouds) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The clouds `spool_clouds` wrote, each a view of one array per episode; the file is deleted."""
    total = sum(spooled.lengths)
    with open(spooled.path, "rb") as f:
        xyz = np.fromfile(f, dtype=np.float32, count=total * 3)
        rgb = np.fromfile(f, dtype=np.uint8, count=total * 3)
    os.unlink(spooled.path)
    if len(xyz) != total * 3 or len(rgb) != total * 3:
        raise OSError(f"{spooled.path}: shorter than the {total} points its reader wrote")
    if not spooled.lengths:
        return [], []
    ends = np.cumsum(spooled.lengths)[:-1]
    return np.split(xyz.reshape(total, 3), ends), np.split(rgb.reshape(total, 3), ends)
