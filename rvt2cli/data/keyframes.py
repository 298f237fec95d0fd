"""Keyframes as types: one `Keyframe` for an annotated keyframe, a predicted one and the executor's
target alike, and the `KeyframeAnnotation` an episode file stores on `/annotations/keyframes`
(schema rvt2.Keyframes). The message is parsed here, once; the rest of rvt2 uses these types.
"""

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Keyframe:
    """A TCP pose to reach, with the gripper state to set there and how to move into it."""

    position: tuple[float, float, float]          # world frame, metres
    quaternion: tuple[float, float, float, float]  # x y z w
    gripper_open: bool
    ignore_collisions: bool                        # plan the motion into it without collision avoidance
    frame: int | None = None                       # where an annotated keyframe is in its episode
    reasons: tuple[str, ...] = ()                  # why the rule chose that frame: gripper, stopped, last

    @staticmethod
    def from_pose(pose7, gripper_open: bool, ignore_collisions: bool, frame: int | None = None,
                  reasons: tuple[str, ...] = ()) -> "Keyframe":
        pose7 = [float(v) for v in pose7]
        return Keyframe(tuple(pose7[:3]), tuple(pose7[3:]), bool(gripper_open), bool(ignore_collisions), frame,
                        tuple(reasons))

    @property
    def pose(self) -> np.ndarray:
        """[7]: x y z qx qy qz qw."""
        return np.array(self.position + self.quaternion)

    def to_json(self) -> dict:
        return {"frame": self.frame, "tcp_pose": list(self.position + self.quaternion), "gripper_open": self.gripper_open,
                "ignore_collisions": self.ignore_collisions, "reasons": list(self.reasons)}

    @staticmethod
    def from_json(obj: dict) -> "Keyframe":
        return Keyframe.from_pose(obj["tcp_pose"], obj["gripper_open"], obj["ignore_collisions"], obj["frame"],
                                  tuple(obj["reasons"]))


@dataclass(frozen=True)
class Sample:
    """A training sample: the observation at `obs_frame`, labelled with keyframe number `keyframe`."""

    obs_frame: int
    keyframe: int


@dataclass(frozen=True)
class KeyframeAnnotation:
    keyframes: tuple[Keyframe, ...]
    samples: tuple[Sample, ...]
    params: dict = field(default_factory=dict)   # the rule's thresholds

    def to_json(self) -> dict:
        return {"params": dict(self.params), "keyframes": [k.to_json() for k in self.keyframes],
                "samples": [{"obs_frame": s.obs_frame, "keyframe": s.keyframe} for s in self.samples]}

    @staticmethod
    def from_json(obj: dict) -> "KeyframeAnnotation":
        return KeyframeAnnotation(keyframes=tuple(Keyframe.from_json(k) for k in obj["keyframes"]),
                                  samples=tuple(Sample(s["obs_frame"], s["keyframe"]) for s in obj["samples"]),
                                  params=dict(obj["params"]))

    def keyframes_reached(self, frame: int) -> int:
        """How many keyframes lie at or before `frame` (the policy's time input there)."""
        return sum(k.frame <= frame for k in self.keyframes)

    def next_keyframe(self, frame: int) -> Keyframe | None:
        return next((k for k in self.keyframes if k.frame > frame), None)

    @property
    def starts(self) -> set[int]:
        """Frames a closed-loop keyframe policy observes: the start and every keyframe."""
        return {0} | {k.frame for k in self.keyframes}
