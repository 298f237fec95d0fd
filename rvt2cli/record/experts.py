"""Scripted experts of our own, where ManiSkill's leave the demonstrations inconsistent or uninformative.

ManiSkill's peg-insertion expert re-aims the peg three times from its measured pose in the hand, then
inserts towards a pose computed from where the peg lay on the table before the grasp: the insertion
runs slanted against the hole's axis by however far the peg sat differently in the hand, and its
screw motions (0.1 rad joint steps) leave the straight line by millimetres, against a 3 mm clearance.
Its demonstrations teach a policy a final keyframe it cannot read off the scene.

`insert_peg` keeps the expert's strategy (grasp, align the peg 1 cm before the hole's face, re-aim
three times) and changes three things: every straight-line motion is planned in 0.01 rad joint steps
and held until the arm rests (but for the grasp, which the closing fingers end, and the
insertion, which ends the episode); the insertion is the aligned pose pushed straight along the hole's axis,
computed from the peg's measured pose like the re-aiming; and it runs at half speed. The keyframes it
leaves are consistent: the insertion is the last aligned pose plus a push along the peg's own axis.

Measured on seeds 10000-10049 (2-core CPU): ManiSkill's expert succeeds 32/50, this one 43/50 (the
variants tried on the way: full speed 40, half speed 44, the aligned peg 3 cm before the face 42-43).

ManiSkill's pick-cube expert carries the cube to the goal sphere straight from the grasp. A policy
predicts that carry from the observation at the grasp, where the arm reaching down to the cube stands
between the cameras and the sphere whenever the sphere floats near over the cube: in 9 of 50 scenes
(seeds 10000-10049) the four cameras see 40 pixels of it or fewer, in 3 none, and a 10-demo policy fails
most of those scenes by guessing the goal. `pick_cube` lifts the cube and draws it back towards the
robot's base first, a motion that does not depend on the goal, so the carry is predicted from a view
where the arm no longer hides the sphere.
"""

import numpy as np
import sapien

from rvt2cli.record.motions import solver, top_down_grasp

APPROACH_M = 0.01      # the aligned peg's head stops this far before the hole's face (as ManiSkill's)
INSERT_BEYOND_M = 0.05  # the insertion aims this far past the goal: the fingers meet the box first
# The insertion runs at half the expert's speed: the arm's tracking error while it accelerates sags the
# peg by 2-3 mm within the first 10 mm, where it meets the face (3 mm clearance).
INSERT_SLOWDOWN = 0.5
REFINEMENTS = 3
LIFT_M = 0.10          # pick_cube: the grasped cube rises this far...
DRAW_BACK_M = 0.20     # ...and moves this far towards the robot's base before the carry


def insert_peg(env, seed=None):
    """PegInsertionSide-v1: grasp the peg, align it a peg's length before the hole, re-aim from its
    measured pose, push it in along the hole's axis. Returns -1 when a motion cannot be planned."""
    env.reset(seed=seed)
    planner = solver(env, speed=0.75)
    scene = env.unwrapped
    half_length = scene.peg_half_sizes[0, 0].item()

    grasp_pose = top_down_grasp(scene, scene.peg)
    grasp_pose = grasp_pose * sapien.Pose([-max(0.05, half_length / 2 + 0.01), 0, 0])  # towards the tail
    peg_on_table = scene.peg.pose

    if planner.move_to_pose_with_screw(grasp_pose * sapien.Pose([0, 0, -0.05])) == -1:
        return -1
    # no settling before the fingers close: the keyframe rule makes the arrival and the grasp one keyframe
    if planner.move_to_pose_with_screw(grasp_pose, refine_steps=0) == -1:
        return -1
    planner.close_gripper()

    def aimed(peg_goal, tcp_pose):
        """The TCP pose that moves the peg, as it now sits in the hand, to `peg_goal`."""
        return peg_goal * scene.peg.pose.inv() * tcp_pose

    before_hole = scene.goal_pose * sapien.Pose([-APPROACH_M - half_length, 0, 0])
    aligned = before_hole * peg_on_table.inv() * grasp_pose  # first guess: the peg as it lay on the table
    if planner.move_to_pose_with_screw(aligned) == -1:
        return -1
    for _ in range(REFINEMENTS):
        aligned = aimed(before_hole, aligned)
        if planner.move_to_pose_with_screw(aligned) == -1:
            return -1
    planner.planner.joint_vel_limits = planner.planner.joint_vel_limits * INSERT_SLOWDOWN
    planner.planner.joint_acc_limits = planner.planner.joint_acc_limits * INSERT_SLOWDOWN
    # no settling at the end either: the episode's last frame is the insertion's keyframe
    return planner.move_to_pose_with_screw(aimed(scene.goal_pose * sapien.Pose([INSERT_BEYOND_M, 0, 0]), aligned),
                                           refine_steps=0)


def pick_cube(env, seed=None):
    """PickCube-v1: ManiSkill's expert (reach 5 cm above the cube, grasp, carry) with one goal-independent
    motion before the carry: the cube lifted LIFT_M and drawn DRAW_BACK_M towards the robot's base. Its
    motions are insert_peg's (fine joint steps, each held until the arm rests). Returns -1 when a motion
    cannot be planned."""
    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.9)  # ManiSkill's speed; fine steps, which plan the lift where 0.1 rad steps fail
    grasp_pose = top_down_grasp(scene, scene.cube, at=scene.cube.pose.sp.p)  # ManiSkill's: at the cube's centre
    if planner.move_to_pose_with_screw(grasp_pose * sapien.Pose([0, 0, -0.05])) == -1:
        return -1
    if planner.move_to_pose_with_screw(grasp_pose, refine_steps=0) == -1:  # the arrival and the grasp: one keyframe
        return -1
    planner.close_gripper()
    backwards = -scene.agent.robot.pose.to_transformation_matrix()[0, :3, 0].cpu().numpy()  # the base faces +x
    lifted = sapien.Pose(grasp_pose.p + DRAW_BACK_M * backwards + [0, 0, LIFT_M], grasp_pose.q)
    if planner.move_to_pose_with_screw(lifted) == -1:
        return -1
    # no settling at the goal: the episode's last frame is the carry's keyframe
    return planner.move_to_pose_with_screw(sapien.Pose(scene.goal_site.pose.sp.p, grasp_pose.q), refine_steps=0)
