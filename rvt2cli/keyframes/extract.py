"""`rvt2 extract-keyframes`: find an episode's keyframes and training samples and store them in it."""

from dataclasses import dataclass

import numpy as np

from rvt2cli.data import Episode, read_episode, write_keyframes
from rvt2cli.keyframes.rule import (Keyframe, KeyframeParams, find_keyframes, ignore_collisions, next_keyframe_index,
                                    observation_starts)


@dataclass
class Annotation:
    keyframes: dict           # the rvt2.Keyframes message
    starts_without_obs: list[int]  # observation starts the file has no images for (not used as samples)


def label_keyframes(gripper_command, joint_velocities, contacts, tcp_pose,
                    params: KeyframeParams = KeyframeParams()) -> tuple[list[Keyframe], list[dict]]:
    """A dense trajectory's keyframes, and each as its rvt2.Keyframes entry (pose, gripper, collision flag)."""
    gripper_command = np.asarray(gripper_command)
    keyframes = find_keyframes(gripper_command > 0, joint_velocities, params)
    flags = ignore_collisions(contacts, keyframes)
    entries = [{"frame": k.frame, "tcp_pose": [float(v) for v in tcp_pose[k.frame]],
                "gripper_open": bool(gripper_command[k.frame] > 0), "ignore_collisions": flag, "reasons": list(k.reasons)}
               for k, flag in zip(keyframes, flags)]
    return keyframes, entries


def annotate(ep: Episode, params: KeyframeParams = KeyframeParams()) -> Annotation:
    robot = ep.robot
    keyframes, entries = label_keyframes(robot.gripper_command, robot.joint_velocities, robot.contacts, robot.tcp_pose, params)
    have_obs = set(ep.obs_frames)
    starts = observation_starts(ep.num_frames, keyframes, params.obs_every)
    samples = [{"obs_frame": f, "keyframe": next_keyframe_index(f, keyframes)} for f in starts if f in have_obs]
    message = {"params": params.to_dict(), "keyframes": entries, "samples": samples}
    return Annotation(message, [f for f in starts if f not in have_obs])


def extract_file(path, params: KeyframeParams = KeyframeParams(), dry_run: bool = False) -> Annotation:
    annotation = annotate(read_episode(path), params)
    if not dry_run:
        write_keyframes(path, annotation.keyframes)
    return annotation


def describe(annotation: Annotation) -> str:
    kfs = annotation.keyframes["keyframes"]
    parts = []
    for k in kfs:
        tags = "+".join(k["reasons"]) + ("" if k["gripper_open"] else ",closed") + (",ignore-collisions" if k["ignore_collisions"] else "")
        parts.append(f"{k['frame']}({tags})")
    text = f"{len(kfs)} keyframes [{' '.join(parts)}], {len(annotation.keyframes['samples'])} samples"
    if annotation.starts_without_obs:
        text += f"; {len(annotation.starts_without_obs)} observation starts have no images in the file (record with a matching --obs-every)"
    return text

