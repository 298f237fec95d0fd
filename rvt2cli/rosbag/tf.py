"""A bag's TF tree (`/tf` and `/tf_static`), and lookups through it at many times at once.

Each frame has at most one parent. A lookup walks from both frames up to their common ancestor and
composes the transforms on the way; a dynamic transform is interpolated between its two messages
around the time asked for (linearly, and by slerp for the rotation), as tf2 does, and refused when
the nearer of them is further away than the tolerance (a stale transform). Poses are 7 numbers
`x y z qx qy qz qw`: the child frame's pose in its parent.
"""

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from rvt2cli.errors import UserError


@dataclass
class Transforms:
    """N rigid transforms (the pose of a frame in another, at N times)."""

    rotation: Rotation
    translation: np.ndarray   # [N, 3]

    @staticmethod
    def from_poses(poses) -> "Transforms":
        poses = np.atleast_2d(np.asarray(poses, dtype=np.float64))
        return Transforms(Rotation.from_quat(poses[:, 3:]), poses[:, :3])

    @staticmethod
    def identity(n: int) -> "Transforms":
        return Transforms(Rotation.identity(n), np.zeros((n, 3)))

    def __mul__(self, other: "Transforms") -> "Transforms":
        """`a * b`: b's frame expressed through a (the pose of b's child in a's parent)."""
        return Transforms(self.rotation * other.rotation, self.translation + self.rotation.apply(other.translation))

    def inv(self) -> "Transforms":
        inverse = self.rotation.inv()
        return Transforms(inverse, -inverse.apply(self.translation))

    def poses(self) -> np.ndarray:
        return np.concatenate([self.translation, self.rotation.as_quat()], axis=1)


@dataclass
class Edge:
    """The transform from `parent` to one child frame: static, or messages at sorted times."""

    parent: str
    static: bool
    stamps: np.ndarray        # [K] int64 ns (one entry for a static transform, its time unused)
    poses: np.ndarray         # [K, 7]


@dataclass(frozen=True)
class StampedTransform:
    parent: str
    child: str
    stamp_ns: int
    pose: tuple               # x y z qx qy qz qw
    static: bool


def frame_name(frame_id: str) -> str:
    """tf2 ignores a leading slash (a ROS 1 habit some publishers keep)."""
    return frame_id.lstrip("/")


class TransformTree:
    def __init__(self, transforms: list[StampedTransform], where: str, origin_ns: int = 0):
        """`where` names the bag in error messages; times in them count from `origin_ns`."""
        self.where = where
        self.origin_ns = origin_ns
        grouped: dict[str, list[StampedTransform]] = {}
        for t in transforms:
            grouped.setdefault(frame_name(t.child), []).append(t)
        self.edges: dict[str, Edge] = {}
        for child, items in grouped.items():
            parents = sorted({frame_name(t.parent) for t in items})
            if len(parents) > 1:
                raise UserError(f"{where}: frame '{child}' has several parents in the TF tree ({', '.join(parents)}); "
                                "a TF tree gives each frame one parent")
            if len({t.static for t in items}) > 1:
                raise UserError(f"{where}: the transform {parents[0]} -> {child} is on both /tf and /tf_static; "
                                "publish it on one of them")
            if items[0].static:
                items = items[-1:]   # a republished static transform replaces the earlier one
            items = sorted(items, key=lambda t: t.stamp_ns)
            self.edges[child] = Edge(parent=parents[0], static=items[0].static,
                                     stamps=np.array([t.stamp_ns for t in items], dtype=np.int64),
                                     poses=np.array([t.pose for t in items], dtype=np.float64))

    @property
    def frames(self) -> list[str]:
        return sorted(set(self.edges) | {e.parent for e in self.edges.values()})

    def _chain_to_root(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self.edges:
            chain.append(self.edges[chain[-1]].parent)
            if len(chain) > len(self.edges) + 1:
                raise UserError(f"{self.where}: the TF tree has a loop through frame '{frame}'")
        return chain

    def lookup(self, target: str, source: str, stamps_ns, tolerance_s: float) -> np.ndarray:
        """The pose of frame `source` in frame `target` at each time [N] (ns): [N, 7]."""
        target, source = frame_name(target), frame_name(source)
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        known = self.frames
        for frame in (target, source):
            if frame not in known:
                raise UserError(f"{self.where}: no transform {target} -> {source}: frame '{frame}' is not on /tf or "
                                f"/tf_static (frames there: {', '.join(known) or 'none'}); publish it (a camera's hand-eye "
                                "calibration goes on /tf_static), or choose another frame")
        up_from_target, up_from_source = self._chain_to_root(target), self._chain_to_root(source)
        common = next((f for f in up_from_source if f in up_from_target), None)
        if common is None:
            raise UserError(f"{self.where}: no transform {target} -> {source}: they are in separate TF trees (roots "
                            f"'{up_from_target[-1]}' and '{up_from_source[-1]}'); record the transforms that join them: "
                            "the robot's /tf (robot_state_publisher) and each camera's hand-eye calibration on /tf_static")
        source_in_common = self._along(up_from_source[:up_from_source.index(common)], stamps_ns, tolerance_s)
        target_in_common = self._along(up_from_target[:up_from_target.index(common)], stamps_ns, tolerance_s)
        return (target_in_common.inv() * source_in_common).poses()

    def _along(self, frames: list[str], stamps_ns: np.ndarray, tolerance_s: float) -> Transforms:
        """Pose of frames[0] in the parent of frames[-1] (frames listed child first, walking up)."""
        result = Transforms.identity(len(stamps_ns))
        for child in frames:
            result = self._edge_at(child, stamps_ns, tolerance_s) * result
        return result

    def _edge_at(self, child: str, stamps_ns: np.ndarray, tolerance_s: float) -> Transforms:
        edge = self.edges[child]
        if edge.static:
            return Transforms.from_poses(np.repeat(edge.poses, len(stamps_ns), axis=0))
        times = edge.stamps
        after = np.searchsorted(times, stamps_ns)
        lo, hi = np.clip(after - 1, 0, len(times) - 1), np.clip(after, 0, len(times) - 1)
        gap = np.minimum(np.abs(stamps_ns - times[lo]), np.abs(times[hi] - stamps_ns))
        stale = np.flatnonzero(gap > tolerance_s * 1e9)
        if len(stale):
            i = stale[0]
            raise UserError(
                f"{self.where}: stale transform {edge.parent} -> {child} at {(stamps_ns[i] - self.origin_ns) / 1e9:.3f} s: "
                f"the nearest /tf message is {gap[i] / 1e9:.3f} s away (--sync-tolerance {tolerance_s} s); check that "
                "the robot's state publisher ran for the whole recording, or raise --sync-tolerance")
        span = (times[hi] - times[lo]).astype(np.float64)
        alpha = np.divide((stamps_ns - times[lo]).astype(np.float64), span, out=np.zeros(len(stamps_ns)), where=span > 0)
        alpha = np.clip(alpha, 0.0, 1.0)
        a, b = Transforms.from_poses(edge.poses[lo]), Transforms.from_poses(edge.poses[hi])
        turn = (a.rotation.inv() * b.rotation).as_rotvec()
        rotation = a.rotation * Rotation.from_rotvec(alpha[:, None] * turn)
        translation = (1 - alpha[:, None]) * a.translation + alpha[:, None] * b.translation
        return Transforms(rotation, translation)
