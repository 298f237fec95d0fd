"""The motions rvt2-18's pick-and-place experts share: come down on a grasp from above and close; carry
the held object over its goal, lower it, let go and back off upwards. Each motion ends with the arm at
rest (but for the arrival at the grasp, which the closing fingers end), so each is one keyframe."""

import sapien

REACH_ABOVE_M = 0.08  # the open hand arrives this far above its grasp, then comes straight down
RETREAT_M = 0.08      # after letting go the hand backs off this far upwards


def grasp_from_above(planner, grasp: sapien.Pose, above: sapien.Pose | None = None) -> bool:
    """Arrive at `above` (default: REACH_ABOVE_M over `grasp`), come down onto `grasp` and close the gripper.
    False if a motion cannot be planned."""
    if above is None:
        above = sapien.Pose(grasp.p + [0, 0, REACH_ABOVE_M], grasp.q)
    if planner.move_to_pose_with_screw(above) == -1:
        return False
    if planner.move_to_pose_with_screw(grasp, refine_steps=0) == -1:  # the arrival and the grasp: one keyframe
        return False
    planner.close_gripper()
    return True


def place_from_above(planner, over, drop_m: float):
    """Move to the pose `over()` gives, twice: the second time it is re-aimed from where the held object
    now hangs. Then lower drop_m, let go and back off. Returns the last motion's result, or -1."""
    for _ in range(2):
        above = over()
        if planner.move_to_pose_with_screw(above) == -1:
            return -1
    lowered = sapien.Pose(above.p - [0, 0, drop_m], above.q)
    if planner.move_to_pose_with_screw(lowered) == -1:
        return -1
    planner.open_gripper()
    return planner.move_to_pose_with_screw(sapien.Pose(lowered.p + [0, 0, RETREAT_M], lowered.q))
