"""`rvt2 extract-keyframes`: find an episode's keyframes and training samples and store them in it."""

from dataclasses import dataclass

import numpy as np

from rvt2cli import runtime
from rvt2cli.data import Episode, read_episode, write_keyframes
from rvt2cli.data.keyframes import Keyframe, KeyframeAnnotation, Sample
from rvt2cli.errors import UserError
from rvt2cli.keyframes.rule import (KeyframeParams, find_keyframes, ignore_collisions, merge_refinements, next_keyframe_index,
                                    observation_starts)


@dataclass
class Annotation:
    keyframes: KeyframeAnnotation
    starts_without_obs: list[int]  # observation starts the file has no images for (not used as samples)


def label_keyframes(gripper_command, arm_velocities, contacts, tcp_pose,
                    params: KeyframeParams = KeyframeParams(), near=None) -> list[Keyframe]:
    """A dense trajectory's keyframes: where the rule finds them, with the TCP pose, gripper state and
    collision flag there. `arm_velocities` [T, J] are the arm joints' only (not the fingers'); `near`
    [T] the bodies near the robot per frame, where recorded."""
    gripper_command = np.asarray(gripper_command)
    events = merge_refinements(find_keyframes(gripper_command > 0, arm_velocities, params), np.asarray(tcp_pose),
                               params.merge_m, params.merge_deg)
    flags = ignore_collisions(contacts, events, near)
    return [Keyframe.from_pose(tcp_pose[e.frame], gripper_command[e.frame] > 0, flag, e.frame, e.reasons)
            for e, flag in zip(events, flags)]


def annotate_trajectory(num_frames: int, obs_frames, gripper_command, arm_velocities, contacts, tcp_pose, near=None,
                        params: KeyframeParams = KeyframeParams()) -> Annotation:
    """A dense trajectory's keyframes and training samples (observation starts with images in `obs_frames`)."""
    keyframes = label_keyframes(gripper_command, arm_velocities, contacts, tcp_pose, params, near)
    have_obs = set(obs_frames)
    starts = observation_starts(num_frames, keyframes, params.obs_every)
    samples = tuple(Sample(f, next_keyframe_index(f, keyframes)) for f in starts if f in have_obs)
    annotation = KeyframeAnnotation(keyframes=tuple(keyframes), samples=samples, params=params.to_dict())
    return Annotation(annotation, [f for f in starts if f not in have_obs])


def annotate(ep: Episode, params: KeyframeParams = KeyframeParams()) -> Annotation:
    robot = ep.robot
    arm_velocities = ep.meta.robot.arm(robot.joint_velocities, robot.joint_names, str(ep.path))
    return annotate_trajectory(ep.num_frames, ep.obs_frames, robot.gripper_command, arm_velocities, robot.contacts,
                               robot.tcp_pose, robot.near, params)


def extract_file(path, params: KeyframeParams = KeyframeParams(), dry_run: bool = False) -> Annotation:
    annotation = annotate(read_episode(path), params)
    if not dry_run:
        write_keyframes(path, annotation.keyframes)
    return annotation


def extract_files(paths, params: KeyframeParams = KeyframeParams(), dry_run: bool = False, workers: int = 1):
    """(path, Annotation or the UserError that refused the file) for each file, in the order given, read
    and written by up to `workers` processes (`runtime.map_over_files`)."""
    return zip(paths, runtime.map_over_files(_extract_or_refusal, paths, params, dry_run, workers=workers))


def _extract_or_refusal(path, params: KeyframeParams, dry_run: bool):
    try:
        return extract_file(path, params, dry_run)
    except UserError as e:
        return e


def describe(annotation: Annotation) -> str:
    kfs = annotation.keyframes.keyframes
    parts = []
    for k in kfs:
        tags = "+".join(k.reasons) + ("" if k.gripper_open else ",closed") + (",ignore-collisions" if k.ignore_collisions else "")
        parts.append(f"{k.frame}({tags})")
    text = f"{len(kfs)} keyframes [{' '.join(parts)}], {len(annotation.keyframes.samples)} samples"
    if annotation.starts_without_obs:
        text += f"; {len(annotation.starts_without_obs)} observation starts have no images in the file (record with a matching --obs-every)"
    return text
