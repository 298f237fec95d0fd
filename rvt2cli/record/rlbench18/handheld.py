"""Motions of the experts that use a tool (a stick, a broom): take it by one end, then place it by where it
sits in the hand, turned about the vertical, so that it rakes or sweeps along a straight line."""

import numpy as np
import sapien
from scipy.spatial.transform import Rotation

LIFT_M = 0.10   # the tool rises this far after the grasp (and the fingers come down from this high)


def pick_up(planner, scene, tool, grip) -> bool:
    """Grasp `tool` from above with the fingers closing across it at the point `grip`, and lift it."""
    from rvt2cli.record.experts import _grasp_from_above
    from rvt2cli.record.rlbench18._motions import grasp_from_above

    grasp = _grasp_from_above(scene, tool, at=grip)
    lifted = sapien.Pose(grasp.p + [0, 0, LIFT_M], grasp.q)
    return grasp_from_above(planner, grasp, above=lifted) and planner.move_to_pose_with_screw(lifted) != -1


def heading(pose: sapien.Pose, axis=(1.0, 0.0, 0.0)) -> float:
    """The yaw (rad) of one of a pose's axes, projected on the table."""
    direction = Rotation.from_quat(pose.q, scalar_first=True).apply(axis)
    return float(np.arctan2(direction[1], direction[0]))


def tcp_for(scene, tool, position, turn: float) -> sapien.Pose:
    """The TCP pose that puts the held `tool`'s origin at `position`, turned by `turn` (rad) about the
    vertical from how it sits now: the tool as it sits in the hand now, moved."""
    now = tool.pose.sp
    rotation = Rotation.from_rotvec([0.0, 0.0, turn]) * Rotation.from_quat(now.q, scalar_first=True)
    goal = sapien.Pose(position, rotation.as_quat(scalar_first=True))
    return goal * now.inv() * scene.agent.tcp.pose.sp


def lower_and_slide(planner, down: sapien.Pose, shift, hover_m: float):
    """From `hover_m` above `down`, lower the held tool there, then slide it by `shift` (m, world frame).
    Returns the last motion's result, -1 if one cannot be planned."""
    for pose in (sapien.Pose(down.p + [0, 0, hover_m], down.q), down):
        if planner.move_to_pose_with_screw(pose) == -1:
            return -1
    # no settling at the end: the episode's last frame is the slide's keyframe
    return planner.move_to_pose_with_screw(sapien.Pose(down.p + np.asarray(shift), down.q), refine_steps=0)
