"""The keyframe rule of PerAct/RVT, written from its description.

A frame is a keyframe when
  - the gripper opens or closes (the command changes between the previous frame and this one),
  - the arm comes to rest: every arm joint velocity is within `stop_velocity` while at the frame
    before some joint was faster (the arm arrives; an arm resting since the start is no keyframe),
    the gripper command has not changed over the surrounding window (two frames before, one after),
    the frame is not the second-to-last, and at least `stop_buffer` frames have passed since the last
    rest keyframe (debounce), or
  - it is the last frame.
Frame 0 is never a keyframe (it is where the episode starts). Finally, a keyframe directly before the
last frame is dropped: the last keyframe already stands for it.
"""

from dataclasses import asdict, dataclass

import numpy as np

ARM_JOINTS = 7  # Panda: the first seven joints are the arm, the rest are the fingers


@dataclass(frozen=True)
class KeyframeParams:
    # rad/s. PerAct/RVT use 0.1 on RLBench; on ManiSkill's 20 Hz PD trajectories 0.1 fires one control
    # step before the arm stops (still ~0.09 rad/s, a few mm short of the pose), 0.02 at the stop.
    stop_velocity: float = 0.02
    stop_buffer: int = 4        # frames a rest keyframe blocks the next one
    obs_every: int = 10         # an observation start every this many frames, besides the keyframes

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Keyframe:
    frame: int
    reasons: tuple[str, ...]  # "gripper", "stopped", "last"


def find_keyframes(gripper_open: np.ndarray, joint_velocities: np.ndarray,
                   params: KeyframeParams = KeyframeParams()) -> list[Keyframe]:
    gripper_open = np.asarray(gripper_open, dtype=bool)
    arm_speed = np.abs(np.asarray(joint_velocities)[:, :ARM_JOINTS]).max(axis=1)
    n = len(gripper_open)
    keyframes: list[Keyframe] = []
    frames_since_stop = params.stop_buffer  # the reference's stopped_buffer, counted upwards
    for i in range(n):
        gripper_steady = 2 <= i < n - 2 and gripper_open[i - 2] == gripper_open[i - 1] == gripper_open[i] == gripper_open[i + 1]
        arrives = i > 0 and arm_speed[i] <= params.stop_velocity < arm_speed[i - 1]
        stopped = frames_since_stop >= params.stop_buffer and arrives and gripper_steady and i != n - 2
        frames_since_stop = 0 if stopped else frames_since_stop + 1
        reasons = []
        if i > 0 and gripper_open[i] != gripper_open[i - 1]:
            reasons.append("gripper")
        if stopped:
            reasons.append("stopped")
        if i == n - 1 and i > 0:
            reasons.append("last")
        if reasons:
            keyframes.append(Keyframe(i, tuple(reasons)))
    if len(keyframes) > 1 and keyframes[-2].frame == keyframes[-1].frame - 1:
        del keyframes[-2]
    return keyframes


def observation_starts(num_frames: int, keyframes: list[Keyframe], obs_every: int) -> list[int]:
    """Frames whose observation starts a training sample: frame 0, every `obs_every`-th frame and
    every keyframe, except those at or after the last keyframe (nothing left to predict)."""
    if not keyframes:
        return []
    last = keyframes[-1].frame
    starts = set(range(0, num_frames, obs_every)) | {k.frame for k in keyframes}
    return sorted(f for f in starts if f < last)


def next_keyframe_index(frame: int, keyframes: list[Keyframe]) -> int:
    """Index of the first keyframe strictly after `frame`."""
    for index, k in enumerate(keyframes):
        if k.frame > frame:
            return index
    raise ValueError(f"no keyframe after frame {frame}")


def ignore_collisions(contacts: list[list[str]], keyframes: list[Keyframe]) -> list[bool]:
    """Per keyframe: did the expert's motion into it make new contact with the scene?

    The motion into keyframe k spans the frames after the previous keyframe (frame 0 for the first)
    up to k. If the robot, or an object it holds, touches a scene body during that motion that it
    was not already touching as the motion began (its first two frames: an object grasped at the
    previous keyframe becomes "held" one frame later, still resting on the table), a
    collision-avoiding planner would have refused the motion, so the executor must plan it with
    collisions ignored (as RLBench's flag means).
    """
    flags = []
    start = 0
    for k in keyframes:
        touching_at_start = set(contacts[start]) | set(contacts[min(start + 1, k.frame)])
        new = set().union(*(set(c) for c in contacts[start + 1:k.frame + 1])) - touching_at_start
        flags.append(bool(new))
        start = k.frame
    return flags
