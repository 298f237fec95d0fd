"""Reach a keyframe with the mplib motion planner, as RLBench's and the ManiSkill experts' executors do.

A keyframe is (TCP pose, gripper open, ignore collisions). The arm moves first, with the gripper as
it is, along a screw motion (a straight line in pose space) or, if that fails, an RRTConnect path;
then the gripper opens or closes. Unless the keyframe says to ignore collisions, both planners avoid
the scene's point cloud (without the robot and the object in its hand). A pose the planners cannot
reach is a failed step, not an error: the arm stays where it is.

Collision avoidance guards the way, not the ends: points within CLEAR_RADIUS of the gripper's start
and goal are dropped, since grasping and placing end (and start) a finger's width from objects, which
a point cloud of 5 mm resolution cannot tell from a collision. When no collision-free path is found
at all, the executor plans once more without the cloud (counted as a collision fallback in the
report): a point cloud cannot tell an object held by its thin edge from an obstacle.
"""

from dataclasses import dataclass

import numpy as np

GRIPPER_STEPS = 6          # control steps to open or close, as the experts do
SETTLE_STEPS = 20          # at most this many extra steps holding the goal, until the arm is at rest
# mplib integrates the screw motion open-loop in joint steps of this size; its default (0.1 rad) ends
# ~1 cm off the goal, 0.01 rad ends within ~1 mm.
SCREW_STEP = 0.01
REST_SPEED = 0.02          # rad/s: the keyframe rule's "at rest" (demo keyframes are where the arm stopped)
COLLISION_RESOLUTION = 0.005  # m, radius of the collision points
CLEAR_RADIUS = 0.06        # m, around the TCP at the start and the goal of a motion


@dataclass(frozen=True)
class KeyframeAction:
    position: np.ndarray       # [3] world, m
    quaternion: np.ndarray     # [4] xyzw
    gripper_open: bool
    ignore_collisions: bool


class StepBudgetExhausted(Exception):
    pass


class Executor:
    def __init__(self, env, step_budget: int, speed: float = 0.9, gripper_close: float = -1.0):
        """`speed`: fraction of the Panda's joint velocity and acceleration limits; `gripper_close`: the
        command that closes the gripper. Both as the task's expert uses them."""
        import mplib

        self.env = env
        u = env.unwrapped
        robot = u.agent.robot
        self.robot = robot
        self.planner = mplib.Planner(
            urdf=u.agent.urdf_path, srdf=u.agent.urdf_path.replace(".urdf", ".srdf"),
            user_link_names=[link.get_name() for link in robot.get_links()],
            user_joint_names=[joint.get_name() for joint in robot.get_active_joints()],
            move_group="panda_hand_tcp",
        )
        base = robot.pose.raw_pose[0].cpu().numpy()
        self.planner.set_base_pose(base)
        self.planner.joint_vel_limits = np.asarray(self.planner.joint_vel_limits) * speed
        self.planner.joint_acc_limits = np.asarray(self.planner.joint_acc_limits) * speed
        self.time_step = u.control_timestep
        self.gripper = 1.0  # open, as every episode starts
        self.gripper_close = gripper_close
        self.steps = 0
        self.step_budget = step_budget
        self.collision_fallbacks = 0
        self.on_step = None  # called after every env.step (videos, rollout recording)

    def _qpos(self) -> np.ndarray:
        return self.robot.get_qpos()[0].cpu().numpy()

    def _step(self, arm_qpos: np.ndarray) -> None:
        if self.steps >= self.step_budget:
            raise StepBudgetExhausted()
        self.env.step(np.hstack([arm_qpos, self.gripper]))
        self.steps += 1
        if self.on_step:
            self.on_step()

    def plan(self, action: KeyframeAction, scene_points: np.ndarray | None) -> dict | None:
        qx, qy, qz, qw = action.quaternion
        target = np.concatenate([action.position, [qw, qx, qy, qz]])
        avoid = not action.ignore_collisions and scene_points is not None and len(scene_points) > 0
        if avoid:
            start = self.env.unwrapped.agent.tcp.pose.p[0].cpu().numpy()
            far = ((np.linalg.norm(scene_points - start, axis=1) > CLEAR_RADIUS)
                   & (np.linalg.norm(scene_points - action.position, axis=1) > CLEAR_RADIUS))
            avoid = bool(far.any())
            if avoid:
                self.planner.update_point_cloud(scene_points[far], radius=COLLISION_RESOLUTION)
        for attempt in ("screw", "rrt"):
            if attempt == "screw":
                result = self.planner.plan_screw(target, self._qpos(), qpos_step=SCREW_STEP, time_step=self.time_step,
                                                 use_point_cloud=avoid)
            else:
                result = self.planner.plan_qpos_to_pose(target, self._qpos(), time_step=self.time_step,
                                                        use_point_cloud=avoid, wrt_world=True)
            if result["status"] == "Success":
                return result
        return None

    def _follow(self, result: dict) -> None:
        arm_joints = len(self.planner.move_group_joint_indices)
        if len(result["position"]) == 0:  # already there (e.g. a gripper keyframe where the arm rests)
            return
        for qpos in result["position"]:
            self._step(qpos[:arm_joints])
        goal = result["position"][-1][:arm_joints]
        for _ in range(SETTLE_STEPS):  # the PD controller lags the path: let the arm arrive
            if np.abs(self.robot.get_qvel()[0, :arm_joints].cpu().numpy()).max() < REST_SPEED:
                break
            self._step(goal)

    def execute(self, action: KeyframeAction, scene_points: np.ndarray | None = None) -> bool:
        """Move to the keyframe and set the gripper. False if no plan reaches the pose (nothing moves).
        Raises StepBudgetExhausted when the episode's control steps run out."""
        result = self.plan(action, scene_points)
        if result is None and scene_points is not None and not action.ignore_collisions:
            result = self.plan(action, None)
            self.collision_fallbacks += result is not None
        if result is None:
            return False
        self._follow(result)
        target_gripper = 1.0 if action.gripper_open else self.gripper_close
        if target_gripper != self.gripper:
            self.gripper = target_gripper
            hold = self._qpos()[:len(self.planner.move_group_joint_indices)]
            for _ in range(GRIPPER_STEPS):
                self._step(hold)
        return True
