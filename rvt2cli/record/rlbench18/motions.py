"""The scripted experts' pick-and-place: reach above, grasp from above, lift, carry over the goal, lower,
let go, back up. Each motion ends at rest, but the arrivals at the grasp and at the release, which the
gripper's change marks as keyframes of their own."""

import numpy as np
import sapien

from rvt2cli.record.experts import _grasp_from_above

REACH_ABOVE = 0.05  # m: the grasp is approached from this far above
DROP = 0.004        # m: an object is let go this far above where it comes to rest


def pick_and_place(planner, scene, actor, goal_xyz, carry_z: float, grasp=None):
    """Move `actor` so that its origin rests at `goal_xyz` (world, m), carried with its origin at height
    `carry_z`, keeping its orientation; `grasp` (a TCP pose) defaults to the top-down grasp of its box.
    Returns the last motion's step result, or -1 when a motion cannot be planned."""
    grasp = _grasp_from_above(scene, actor) if grasp is None else grasp
    if planner.move_to_pose_with_screw(grasp * sapien.Pose([0, 0, -REACH_ABOVE])) == -1:
        return -1
    if planner.move_to_pose_with_screw(grasp, refine_steps=0) == -1:
        return -1
    planner.close_gripper()
    held = actor.pose.sp.p - grasp.p  # the actor's origin from the TCP, world axes (the hand does not turn)
    lifted = sapien.Pose([grasp.p[0], grasp.p[1], carry_z - held[2]], grasp.q)
    above = sapien.Pose([*(np.asarray(goal_xyz[:2]) - held[:2]), lifted.p[2]], grasp.q)
    down = sapien.Pose([above.p[0], above.p[1], goal_xyz[2] + DROP - held[2]], grasp.q)
    for pose in (lifted, above):
        if planner.move_to_pose_with_screw(pose) == -1:
            return -1
    if planner.move_to_pose_with_screw(down, refine_steps=0) == -1:
        return -1
    planner.open_gripper()
    return planner.move_to_pose_with_screw(above)
