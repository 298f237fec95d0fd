"""The motions rvt2's scripted experts are made of: a motion planner that moves in straight lines to
within a fraction of a millimetre, top-down grasps, pick-and-place, and the handling of tools (a stick,
a broom). Each motion ends with the arm at rest, so that each is one keyframe, except where the fingers'
closing or the episode's end marks it instead (`refine_steps=0`).

The straight-line motions are mplib's screw motions, in finer joint steps than ManiSkill's experts take:
ManiSkill's 0.1 rad steps leave the straight line by millimetres, against an insertion's 3 mm clearance.
"""

import numpy as np
import sapien
from scipy.spatial.transform import Rotation

SCREW_STEP = 0.01     # rad: joint steps of the straight-line motions (ManiSkill's experts use 0.1)
COARSE_SCREW_STEP = 0.1
MERE_TURN_RAD = np.radians(0.5)  # a screw motion that fails on a turn this small is retried as a shift
SETTLE_STEPS = 10     # control steps holding each motion's last command, so the arm rests where it stopped
FINGER_LENGTH = 0.025  # m: how deep a top-down grasp takes an object between the fingers

REACH_ABOVE_M = 0.08  # grasp_from_above: the open hand arrives this far above its grasp, then comes straight down
RETREAT_M = 0.08      # place_from_above: after letting go the hand backs off this far upwards
PICK_REACH_M = 0.05   # pick_and_place: the grasp is approached from this far above
DROP_M = 0.004        # pick_and_place: an object is let go this far above where it comes to rest
TOOL_LIFT_M = 0.10    # pick_up_tool: the tool rises this far after the grasp (and the fingers come down from this high)


def solver(env, speed: float):
    """ManiSkill's Panda motion-planning solver at `speed` (a fraction of the joints' velocity and
    acceleration limits), with finer screw motions that end at rest."""
    from mani_skill.examples.motionplanning.panda.motionplanner import PandaArmMotionPlanningSolver

    class PreciseSolver(PandaArmMotionPlanningSolver):
        def move_to_pose_with_screw(self, pose, dry_run: bool = False, refine_steps: int = SETTLE_STEPS):
            from mani_skill.utils.structs.pose import to_sapien_pose

            target = self._transform_pose_for_planning(to_sapien_pose(pose))
            result = self._plan(target)
            if result is None:
                # mplib's screw motion can fail on the hair's-breadth turn (hundredths of a degree) left between
                # the orientation the arm holds and the one it was sent to: keep the one it holds
                here = self.base_env.agent.tcp.pose.sp
                if (here.inv() * target).to_transformation_matrix()[:3, :3].trace() > 1 + 2 * np.cos(MERE_TURN_RAD):
                    result = self._plan(sapien.Pose(target.p, here.q))
            if result is None:
                return -1
            return result if dry_run else self.follow_path(result, refine_steps=refine_steps)

        def _plan(self, target):
            for step in (SCREW_STEP, COARSE_SCREW_STEP):  # fine steps check more states: fall back to ManiSkill's
                try:
                    result = self.planner.plan_screw(np.concatenate([target.p, target.q]),
                                                     self.robot.get_qpos().cpu().numpy()[0],
                                                     time_step=self.base_env.control_timestep, qpos_step=step,
                                                     use_point_cloud=self.use_point_cloud)
                except RuntimeError:  # toppra cannot time a path of a few tiny steps ("not controllable")
                    continue
                if result["status"] == "Success":
                    return result
            return None

    return PreciseSolver(env, debug=False, vis=False, base_pose=env.unwrapped.agent.robot.pose,
                         visualize_target_grasp_pose=False, print_env_info=False,
                         joint_vel_limits=speed, joint_acc_limits=speed)


# Grasps and pick-and-place

def top_down_grasp(scene, actor, at=None) -> sapien.Pose:
    """ManiSkill's top-down grasp of `actor`: the TCP pose with the fingers closing across its bounding
    box, nearest the way the open gripper faces now, FINGER_LENGTH deep, centred `at` (default: the box's
    grasp centre)."""
    from mani_skill.examples.motionplanning.base_motionplanner.utils import compute_grasp_info_by_obb, get_actor_obb

    approaching = np.array([0, 0, -1])
    closing = scene.agent.tcp.pose.to_transformation_matrix()[0, :3, 1].cpu().numpy()
    grasp = compute_grasp_info_by_obb(get_actor_obb(actor), approaching=approaching, target_closing=closing,
                                      depth=FINGER_LENGTH)
    return scene.agent.build_grasp_pose(approaching, grasp["closing"], grasp["center"] if at is None else at)


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


def pick_and_place(planner, scene, actor, goal_xyz, carry_z: float, grasp=None):
    """Reach above, grasp from above, lift, carry over the goal, lower, let go, back up: move `actor` so
    that its origin rests at `goal_xyz` (world, m), carried with its origin at height `carry_z`, keeping
    its orientation; `grasp` (a TCP pose) defaults to the top-down grasp of its box. Returns the last
    motion's step result, or -1 when a motion cannot be planned."""
    grasp = top_down_grasp(scene, actor) if grasp is None else grasp
    if planner.move_to_pose_with_screw(grasp * sapien.Pose([0, 0, -PICK_REACH_M])) == -1:
        return -1
    if planner.move_to_pose_with_screw(grasp, refine_steps=0) == -1:
        return -1
    planner.close_gripper()
    held = actor.pose.sp.p - grasp.p  # the actor's origin from the TCP, world axes (the hand does not turn)
    lifted = sapien.Pose([grasp.p[0], grasp.p[1], carry_z - held[2]], grasp.q)
    above = sapien.Pose([*(np.asarray(goal_xyz[:2]) - held[:2]), lifted.p[2]], grasp.q)
    down = sapien.Pose([above.p[0], above.p[1], goal_xyz[2] + DROP_M - held[2]], grasp.q)
    for pose in (lifted, above):
        if planner.move_to_pose_with_screw(pose) == -1:
            return -1
    if planner.move_to_pose_with_screw(down, refine_steps=0) == -1:
        return -1
    planner.open_gripper()
    return planner.move_to_pose_with_screw(above)


# Tools: take one by one end, then place it by where it sits in the hand, turned about the vertical, so
# that it rakes or sweeps along a straight line.

def pick_up_tool(planner, scene, tool, grip) -> bool:
    """Grasp `tool` from above with the fingers closing across it at the point `grip`, and lift it."""
    grasp = top_down_grasp(scene, tool, at=grip)
    lifted = sapien.Pose(grasp.p + [0, 0, TOOL_LIFT_M], grasp.q)
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
