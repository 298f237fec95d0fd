"""Match message streams to a clock by header stamp.

The clock is the first camera's colour stream: frame t is its t-th image. Every other stream gives
each frame its message nearest in time, which must lie within the tolerance. Frames before every
stream has started, or after one has ended, cannot be matched and are cut off the episode's ends;
a gap inside the episode is an error.
"""

from dataclasses import dataclass

import numpy as np


@dataclass
class Stream:
    name: str                 # a topic, or "topic (joint name)"
    stamps: np.ndarray        # int64 ns, sorted ascending


@dataclass
class Unmatched:
    """The first frame without a message within the tolerance."""

    frame: int
    gap_ns: int


def common_span(clock: np.ndarray, streams: list[Stream], tolerance_ns: int) -> tuple[int, int]:
    """The frames [first, last) of `clock` during which every stream has started and not yet ended."""
    start = max(s.stamps[0] for s in streams) - tolerance_ns
    end = min(s.stamps[-1] for s in streams) + tolerance_ns
    return int(np.searchsorted(clock, start, side="left")), int(np.searchsorted(clock, end, side="right"))


def nearest(stream: Stream, clock: np.ndarray, tolerance_ns: int) -> tuple[np.ndarray, Unmatched | None]:
    """For every clock time, the index of the stream's message nearest to it; and the first frame
    whose nearest message is further away than the tolerance (None when every frame is matched)."""
    after = np.searchsorted(stream.stamps, clock)
    before = np.clip(after - 1, 0, len(stream.stamps) - 1)
    after = np.clip(after, 0, len(stream.stamps) - 1)
    take_after = np.abs(stream.stamps[after] - clock) < np.abs(clock - stream.stamps[before])
    index = np.where(take_after, after, before)
    gaps = np.abs(stream.stamps[index] - clock)
    late = np.flatnonzero(gaps > tolerance_ns)
    unmatched = Unmatched(int(late[0]), int(gaps[late[0]])) if len(late) else None
    return index, unmatched
