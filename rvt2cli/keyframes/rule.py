"""The keyframe rule of PerAct/RVT, written from its description, made exact for 20 Hz PD control.

A frame is a keyframe when
  - the gripper opens or closes (the command changes between the previous frame and this one),
  - the arm comes to rest (`stopped`), or
  - it is the last frame.
Frame 0 is never a keyframe (it is where the episode starts), and a keyframe directly before the last
frame is dropped: the last keyframe already stands for it.

The arm comes to rest where every arm joint slows below `stop_velocity` (0.02 rad/s), having been
faster the frame before (the arm arrives; an arm resting since the start is no keyframe). PerAct/RVT
use 0.1 rad/s on RLBench; on ManiSkill's 20 Hz PD trajectories that fires a control step or three
before the arm stops, a few mm short of where it stops. But where a scripted expert chains motions
(lift, then turn, then lower) the arm only pauses between them, never as slow as 0.02: such a pause, a
stretch slower than `pause_velocity` (0.05) that never gets slower than `stop_velocity` and after
which the arm moves on, is a keyframe at its slowest frame. (A brief slow-down while pushing against
a contact, around 0.1 rad/s, is not.) A rest keyframe also needs the gripper command unchanged over the surrounding
window (two frames before, one after), is never the second-to-last frame, and comes more than
`stop_buffer` frames after the previous rest keyframe (debounce), and no more than `stop_buffer` frames
before a gripper or last keyframe (that one stands for it).
"""

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class KeyframeParams:
    stop_velocity: float = 0.02   # rad/s: slower than this, the arm has stopped
    pause_velocity: float = 0.05  # rad/s: a stretch slower than this, between two motions, is a pause
    stop_buffer: int = 4         # frames a rest keyframe blocks the next one
    obs_every: int = 10          # an observation start every this many frames, besides the keyframes
    merge_m: float = 0.0         # > 0: a rest keyframe that the next rest keyframe corrects by less than this...
    merge_deg: float = 5.0       # ...and turns by less than this is dropped (a turn in place is a motion of its own)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class KeyframeEvent:
    """Where the rule found a keyframe, and why."""

    frame: int
    reasons: tuple[str, ...]  # "gripper", "stopped", "last"


def rest_frames(arm_speed: np.ndarray, params: KeyframeParams) -> list[int]:
    """Where the arm comes to rest (before the gripper and debounce checks): every frame where it
    slows below `stop_velocity` (having been faster the frame before), and, in a slow stretch below
    `pause_velocity` that never gets that slow and after which the arm speeds up again (a pause between
    chained motions), its slowest frame."""
    n = len(arm_speed)
    arrivals = [i for i in range(1, n) if arm_speed[i] <= params.stop_velocity < arm_speed[i - 1]]
    pauses = []
    slow = arm_speed <= params.pause_velocity
    i = 1
    while i < n:
        if slow[i] and not slow[i - 1]:
            end = i
            while end + 1 < n and slow[end + 1]:
                end += 1
            stretch = arm_speed[i:end + 1]
            resumes = end + 1 < n  # a pause ends with the arm moving again (the episode's end is the last keyframe)
            if resumes and stretch.min() > params.stop_velocity:
                pauses.append(i + int(np.argmin(stretch)))
            i = end + 1
        else:
            i += 1
    return sorted(arrivals + pauses)


def find_keyframes(gripper_open: np.ndarray, arm_velocities: np.ndarray,
                   params: KeyframeParams = KeyframeParams()) -> list[KeyframeEvent]:
    """gripper_open [T] and the arm joints' velocities [T, J] (not the fingers') of a dense trajectory."""
    gripper_open = np.asarray(gripper_open, dtype=bool)
    arm_speed = np.abs(np.asarray(arm_velocities)).max(axis=1)
    n = len(gripper_open)
    stops = set()
    last_stop = None
    for i in rest_frames(arm_speed, params):
        gripper_steady = 2 <= i < n - 2 and gripper_open[i - 2] == gripper_open[i - 1] == gripper_open[i] == gripper_open[i + 1]
        debounced = last_stop is not None and i - last_stop <= params.stop_buffer
        if gripper_steady and i != n - 2 and not debounced:
            stops.add(i)
            last_stop = i
    keyframes: list[KeyframeEvent] = []
    for i in range(1, n):
        reasons = []
        if gripper_open[i] != gripper_open[i - 1]:
            reasons.append("gripper")
        if i in stops:
            reasons.append("stopped")
        if i == n - 1:
            reasons.append("last")
        if reasons:
            keyframes.append(KeyframeEvent(i, tuple(reasons)))
    if len(keyframes) > 1 and keyframes[-2].frame == keyframes[-1].frame - 1:
        del keyframes[-2]
    # An arrival a few frames before the gripper acts or the episode ends is the same pose: the later
    # keyframe stands for it (else the motion into the grasp, or the insertion, would be split in two, and
    # its collision flag would depend on where this demo happened to stop)
    return [k for k, following in zip(keyframes, keyframes[1:] + [None])
            if not (k.reasons == ("stopped",) and following is not None and following.frame - k.frame <= params.stop_buffer
                    and {"gripper", "last"} & set(following.reasons))]


def merge_refinements(keyframes: list[KeyframeEvent], tcp_poses: np.ndarray, merge_m: float,
                      merge_deg: float = 5.0) -> list[KeyframeEvent]:
    """Drop each rest keyframe that the following rest keyframe (same gripper state: nothing happened
    between them) moves by less than `merge_m` and turns by less than `merge_deg`: a scripted expert's
    re-aiming in small steps (25, 10, 3, 1 mm and 0.2-2 degrees before an insertion) becomes one
    keyframe, its last, so that the observation before an insertion has one next keyframe, not a choice
    between another correction and the insertion. A turn in place (lift_peg_upright's 36 degrees at 4
    mm) is a motion of its own and stays. `tcp_poses` [T, 7]: x y z qx qy qz qw."""
    if merge_m <= 0:
        return keyframes
    from scipy.spatial.transform import Rotation

    def small(a: int, b: int) -> bool:
        turn = Rotation.from_quat(tcp_poses[a, 3:]).inv() * Rotation.from_quat(tcp_poses[b, 3:])
        return (np.linalg.norm(tcp_poses[b, :3] - tcp_poses[a, :3]) < merge_m
                and np.degrees(turn.magnitude()) < merge_deg)

    kept = []
    for k, following in zip(keyframes, keyframes[1:] + [None]):
        refined = (following is not None and k.reasons == ("stopped",) and following.reasons == ("stopped",)
                   and small(k.frame, following.frame))
        if not refined:
            kept.append(k)
    return kept


def observation_starts(num_frames: int, keyframes: list[KeyframeEvent], obs_every: int) -> list[int]:
    """Frames whose observation starts a training sample: frame 0, every `obs_every`-th frame and
    every keyframe, except those at or after the last keyframe (nothing left to predict)."""
    if not keyframes:
        return []
    last = keyframes[-1].frame
    starts = set(range(0, num_frames, obs_every)) | {k.frame for k in keyframes}
    return sorted(f for f in starts if f < last)


def next_keyframe_index(frame: int, keyframes: list[KeyframeEvent]) -> int:
    """Index of the first keyframe strictly after `frame`."""
    for index, k in enumerate(keyframes):
        if k.frame > frame:
            return index
    raise ValueError(f"no keyframe after frame {frame}")


def ignore_collisions(contacts: list[list[str]], keyframes: list[KeyframeEvent],
                      near: list[list[str]] | None = None) -> list[bool]:
    """Per keyframe: may the motion into it touch the scene (RLBench's "ignore collisions")?

    The motion into keyframe k spans the frames after the previous keyframe (frame 0 for the first)
    up to k. It ignores collisions when
      - the robot, or an object it holds, touches a scene body during the motion that it was not
        already touching as the motion began (its first two frames: an object grasped at the previous
        keyframe becomes "held" one frame later, still resting on the table), or
      - the motion ends near a body (within `rvt2cli.record.scene.NEAR_M`, the planner's collision
        radius; `near` per frame) that it was not near as it began.
    Either way a collision-avoiding planner would have refused the motion. The second clause makes the
    flag mean the same thing in every demo: an insertion into a close fit (a charger's 0.5 mm) or a
    grasp ends within millimetres of the fit's walls or the object, whether or not this demo's motion
    happened to brush them. Episodes recorded without `near` are labelled by contacts alone.
    """
    flags = []
    start = 0
    for k in keyframes:
        second = min(start + 1, k.frame)
        touching_at_start = set(contacts[start]) | set(contacts[second])
        new = set().union(*(set(c) for c in contacts[start + 1:k.frame + 1])) - touching_at_start
        arrives_near = near is not None and bool(set(near[k.frame]) - set(near[start]) - set(near[second]))
        flags.append(bool(new) or arrives_near)
        start = k.frame
    return flags
