"""Reach keyframes in the simulator: a motion planner for the way, a joint servo for the last millimetre.

A keyframe (`rvt2cli.data.keyframes.Keyframe`) is a TCP pose, the gripper state to set there, and
whether the motion into it may touch the scene. The executor
1. plans the way with mplib, as RLBench's and the ManiSkill experts' executors do: a screw motion (a
   straight line in pose space), or else an RRTConnect path; unless the keyframe says to ignore
   collisions, both avoid the scene's point cloud (without the robot and the object in its hand);
2. follows the path, with its end corrected to the exact inverse-kinematics solution of the target:
   mplib integrates the screw motion open-loop in joint steps and ends 1-3 mm off the target, which is
   as much as a peg's clearance. The correction is blended in along the path, so the motion stays smooth;
3. servos in joint space until the TCP is at rest within `Tolerance` of the target: it holds the IK
   solution and, where the arm rests elsewhere (an object in the hand, a contact), shifts the joint
   command by the remaining joint error (integral action, bounded), for at most `SERVO_STEPS` steps,
   and, for a keyframe that avoids collisions, stops early once the error has not shrunk for
   `STALL_STEPS` steps (a pose blocked by an unexpected contact, whether the arm rests against it or
   trembles there, comes no closer).
   A real Franka under Cartesian impedance control lands well under a millimetre; so does this;
4. opens or closes the gripper.
Every keyframe reports where the TCP came to rest (`Reach`). A pose the planners cannot reach is a
failed step, not an error: nothing moves.

An insertion (a keyframe that ignores collisions, with the gripper closed before and after it) is pushed
along a straight line that stops at a contact; where the held object stops at a face short of the keyframe,
the executor searches for the hole around it (`rvt2cli.eval.search`) before it servos.

Collision avoidance guards the way, not the ends (`rvt2cli.eval.robot_geometry`): the planner's cloud
leaves out every point within CLEARANCE of the robot's links as it stands (the wrist camera's housing
included), and of the gripper's links where the gripper will stand at the goal, since grasping and
placing end (and start) a finger's width from objects, which a point cloud of 5 mm resolution cannot
tell from a collision. When no collision-free path is found at all, the executor plans once more
without the cloud (counted as a collision fallback): a point cloud cannot tell an object held by its
thin edge from an obstacle.

A pose the arm cannot take exactly (no inverse-kinematics solution within the joint limits, typically
a prediction a few millimetres beyond the arm's reach) is replaced by the nearest pose it can take, if
that is within REACH_SLACK: a real arm under Cartesian control goes as far as it can, and the error
is reported against the pose asked for. Further off, the keyframe is unreachable (`Reach.why`).
"""

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from rvt2cli.data.keyframes import Keyframe
from rvt2cli.eval.robot_geometry import RobotGeometry
from rvt2cli.eval.search import (BLOCKED_M, CONTACT_LAG_M, CONTACT_SPEED_SHARE, ENTERED_M, INSIDE_M, PROBE_M,
                                 InsertionSearch, across)
from rvt2cli.record.scene import tcp_pose
from rvt2cli.robot import RobotFacts, planner_description

GRIPPER_STEPS = 6          # control steps to open or close, as the experts do
SETTLE_STEPS = 20          # at most this many steps holding the goal until the arm is at rest (no servo needed)
SERVO_STEPS = 40           # at most this many further steps of servoing onto the target
# A collision-avoiding keyframe whose error has not shrunk by 5% in this many servo steps is blocked by
# something its plan did not expect: stop pushing. A collision-ignoring one (an insertion, a push) keeps
# pushing for all SERVO_STEPS: a peg that sticks at a hole's rim often slides in a few steps later.
STALL_STEPS = 8
MAX_SERVO_OFFSET = 0.05    # rad: the furthest the servo moves a joint command away from the IK solution
# mplib integrates the screw motion open-loop in joint steps of this size; its default (0.1 rad) ends
# ~1 cm off the goal, 0.01 rad within a few mm (the IK correction removes the rest).
SCREW_STEP = 0.01
MAX_CORRECTION = 0.1       # rad: a larger IK correction of a path's end means another IK branch: not blended in
REST_SPEED = 0.02          # rad/s: the keyframe rule's "at rest" (demo keyframes are where the arm stopped)
COLLISION_RESOLUTION = 0.005  # m, radius of the collision points
CLEARANCE = COLLISION_RESOLUTION + 0.005  # m: cloud points this close to the robot at a motion's ends are left out
REACH_SLACK_M = 0.02       # the nearest pose the arm can take stands in for a target at most this far...
REACH_SLACK_DEG = 5.0      # ...and this much turned from it
UNREACHABLE = ("no_ik", "no_path")   # Reach.why: no pose within REACH_SLACK; a pose, but no plan to it


@dataclass(frozen=True)
class Tolerance:
    """How close the TCP must come to rest to a keyframe before the servo stops."""

    position_m: float = 0.0002
    rotation_deg: float = 0.1


@dataclass(frozen=True)
class Reach:
    """What became of one keyframe."""

    reached: bool                       # False: no plan reached the pose, and nothing moved
    position_error_mm: float | None     # where the TCP came to rest, against the target (None if not reached)
    rotation_error_deg: float | None
    planner: str                        # "screw", "rrt", or "none" (no plan)
    collision_fallback: bool = False    # reached only by planning without the scene cloud
    servo_steps: int = 0                # control steps spent servoing after the path
    why: str | None = None              # unreached: one of UNREACHABLE
    nearest: bool = False               # the target was out of reach: went to the nearest pose within REACH_SLACK
    start_in_collision: bool = False    # the planner's cloud touched the robot where it stood (should never be)
    probes: int = 0                     # probes of the insertion search (0: the push was not stopped at a face)
    search_offset_mm: float | None = None  # where a probe went in: its distance across the push from the keyframe
    interrupted: bool = False           # the episode's control steps ran out during this keyframe

    @staticmethod
    def unreachable(why: str, start_in_collision: bool = False) -> "Reach":
        return Reach(False, None, None, "none", why=why, start_in_collision=start_in_collision)


class StepBudgetExhausted(Exception):
    """The episode's control steps ran out; `reach`: where the keyframe being executed got to."""

    def __init__(self, reach: "Reach | None" = None):
        super().__init__("the episode's control steps ran out")
        self.reach = reach


def rigid_transform(position, quaternion_xyzw) -> np.ndarray:
    """4x4 rigid transform."""
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_quat(quaternion_xyzw).as_matrix()
    transform[:3, 3] = position
    return transform


def _mplib_transform(pose: np.ndarray) -> np.ndarray:
    """4x4 transform of a pose as mplib writes it: [x y z qw qx qy qz]."""
    return rigid_transform(pose[:3], [*pose[4:7], pose[3]])


def _timed_path(plan) -> dict | None:
    """mplib's result of `plan()` if it found a path and timed it, else None. Its TOPP-RA step raises on
    a path it cannot time within the joints' speed and acceleration limits ("Fail to parameterize path");
    for the executor that is one more path it cannot follow, not a broken episode."""
    try:
        result = plan()
    except RuntimeError as error:
        if "parameterize" not in str(error):
            raise
        return None
    return result if result["status"] == "Success" else None


def pose_error(pose7: np.ndarray, target: Keyframe) -> tuple[float, float]:
    """(position error in m, rotation error in degrees) of a TCP pose [x y z qx qy qz qw] to a keyframe."""
    position = float(np.linalg.norm(np.asarray(pose7[:3]) - np.asarray(target.position)))
    rotation = Rotation.from_quat(pose7[3:]).inv() * Rotation.from_quat(target.quaternion)
    return position, float(np.degrees(rotation.magnitude()))


class Executor:
    def __init__(self, env, step_budget: int, speed: float = 0.9, gripper_close: float = -1.0,
                 tolerance: Tolerance = Tolerance(), search: InsertionSearch | None = None):
        """`speed`: fraction of the robot's joint velocity and acceleration limits; `gripper_close`: the
        command that closes the gripper. Both as the task's expert uses them. `search`: how to look for the
        hole when an insertion stops at a face (None: push straight only)."""
        import mplib

        self.env = env
        agent = env.unwrapped.agent
        self.robot = agent.robot
        self.facts = RobotFacts.from_agent(agent)
        urdf, srdf = planner_description(agent)
        self.geometry = RobotGeometry.from_urdf(urdf, self.facts.arm_joints[-1])
        self.joint_names = [joint.get_name() for joint in self.robot.get_active_joints()]
        self.planner = mplib.Planner(urdf=urdf, srdf=srdf, user_link_names=[link.get_name() for link in self.robot.get_links()],
                                     user_joint_names=self.joint_names, move_group=self.facts.tcp_link)
        self.planner.set_base_pose(self.robot.pose.raw_pose[0].cpu().numpy())
        self.planner.joint_vel_limits = np.asarray(self.planner.joint_vel_limits) * speed
        self.planner.joint_acc_limits = np.asarray(self.planner.joint_acc_limits) * speed
        self.arm = self.facts.indices(self.joint_names, self.facts.arm_joints)
        self.fingers = self.facts.indices(self.joint_names, self.facts.finger_joints)
        self.tcp_index = self.planner.link_name_2_idx[self.facts.tcp_link]
        self.finger_mask = [i not in set(self.arm.tolist()) for i in range(len(self.joint_names))]
        self.time_step = env.unwrapped.control_timestep
        self.tolerance = tolerance
        self.search = search
        self.probes = 0  # probes of the insertion search at the keyframe being executed
        self.gripper = 1.0  # open, as every episode starts
        self.gripper_close = gripper_close
        self.steps = 0
        self.start_collided = False  # the planner's start state touched its cloud during this keyframe's planning
        self.step_budget = step_budget
        self.on_step = None  # called after every env.step (videos, rollout recording)

    # --- the robot's state -------------------------------------------------------------------------
    def qpos(self) -> np.ndarray:
        return self.robot.get_qpos()[0].cpu().numpy()

    def finger_positions(self) -> np.ndarray:
        return self.qpos()[self.fingers]

    def tcp_pose(self) -> np.ndarray:
        return tcp_pose(self.env).astype(np.float64)

    def _along(self, direction: np.ndarray) -> float:
        """Where the TCP is along a unit direction (m)."""
        return float(self.tcp_pose()[:3] @ direction)

    def _at_rest(self) -> bool:
        return float(np.abs(self.robot.get_qvel()[0].cpu().numpy()[self.arm]).max()) < REST_SPEED

    def _step(self, arm_qpos: np.ndarray) -> None:
        if self.steps >= self.step_budget:
            raise StepBudgetExhausted()
        self.env.step(np.hstack([arm_qpos, self.gripper]))
        self.steps += 1
        if self.on_step:
            self.on_step()

    # --- planning ------------------------------------------------------------------------------------
    @staticmethod
    def _mplib_pose(target: Keyframe) -> np.ndarray:
        qx, qy, qz, qw = target.quaternion
        return np.array([*target.position, qw, qx, qy, qz])

    def _world_pose(self, link_index: int) -> np.ndarray:
        """4x4 world pose of a link after `pinocchio_model.compute_forward_kinematics` (which works in the
        robot's base frame)."""
        base = _mplib_transform(self.planner.robot.get_base_pose())
        return base @ _mplib_transform(self.planner.pinocchio_model.get_link_pose(link_index))

    def link_poses(self, qpos: np.ndarray) -> dict[str, np.ndarray]:
        """World pose (4x4) of every link with collision geometry, at the full joint vector `qpos`."""
        self.planner.pinocchio_model.compute_forward_kinematics(np.asarray(qpos, dtype=np.float64))
        return {name: self._world_pose(self.planner.link_name_2_idx[name]) for name in self.geometry.hulls}

    def clear_cloud(self, scene_points: np.ndarray, target: Keyframe) -> np.ndarray:
        """The scene points a plan to `target` must avoid: not those at the robot as it stands, nor
        those at the gripper's links where they will stand at the target."""
        start = self.link_poses(self.qpos())
        now = self.tcp_pose()
        move = rigid_transform(target.position, target.quaternion) @ np.linalg.inv(rigid_transform(now[:3], now[3:]))
        goal = {name: move @ pose for name, pose in start.items() if name in self.geometry.rides_with_tcp}
        near = self.geometry.near(scene_points, start, CLEARANCE) | self.geometry.near(scene_points, goal, CLEARANCE)
        return scene_points[~near]

    def _start_in_collision(self) -> bool:
        return len(self.planner.check_for_env_collision(qpos=self.qpos(), with_point_cloud=True)) > 0

    def _screw(self, target: Keyframe, use_point_cloud: bool) -> dict | None:
        """mplib's straight-line (screw) motion from where the arm stands to the target, or None."""
        return _timed_path(lambda: self.planner.plan_screw(self._mplib_pose(target), self.qpos(), qpos_step=SCREW_STEP,
                                                           time_step=self.time_step, use_point_cloud=use_point_cloud))

    def plan(self, target: Keyframe, scene_points: np.ndarray | None) -> tuple[str, dict] | None:
        """(planner name, mplib result) of a motion to the target, or None."""
        goal = self._mplib_pose(target)
        avoid = not target.ignore_collisions and scene_points is not None and len(scene_points) > 0
        if avoid:
            kept = self.clear_cloud(scene_points, target)
            avoid = len(kept) > 0
            if avoid:
                self.planner.update_point_cloud(kept, radius=COLLISION_RESOLUTION)
                self.start_collided = self.start_collided or self._start_in_collision()
        result = self._screw(target, avoid)
        if result is not None:
            return "screw", result
        result = _timed_path(lambda: self.planner.plan_qpos_to_pose(goal, self.qpos(), time_step=self.time_step,
                                                                    use_point_cloud=avoid, wrt_world=True))
        if result is not None:
            return "rrt", result
        return None

    def inverse_kinematics(self, target: Keyframe, near: np.ndarray) -> np.ndarray | None:
        """The arm joints that put the TCP exactly on the target, found from the full joint vector `near`
        (closed-loop IK, deterministic); None if it does not converge within the joint limits."""
        goal = self.planner.transform_goal_to_wrt_base(self._mplib_pose(target))
        q, converged, _ = self.planner.pinocchio_model.compute_IK_CLIK(self.tcp_index, goal, near.astype(np.float64),
                                                                         self.finger_mask)
        limits = np.asarray(self.planner.joint_limits)[self.arm]
        arm = q[self.arm]
        if not converged or np.any(arm < limits[:, 0] - 1e-6) or np.any(arm > limits[:, 1] + 1e-6):
            return None
        return arm

    def nearest_reachable(self, target: Keyframe) -> Keyframe | None:
        """The pose nearest to the target that the arm can take (closed-loop IK clamped to the joint
        limits, from where the arm stands), if it is within REACH_SLACK of the target; else None."""
        limits = np.asarray(self.planner.joint_limits)
        model = self.planner.pinocchio_model
        goal = self.planner.transform_goal_to_wrt_base(self._mplib_pose(target))
        # damped: at the edge of the workspace (a singular arm) undamped steps diverge
        q, _, _ = model.compute_IK_CLIK_JL(self.tcp_index, goal, self.qpos().astype(np.float64), limits[:, 0], limits[:, 1],
                                           max_iter=3000, damp=1e-3)
        model.compute_forward_kinematics(q)
        pose = self._world_pose(self.tcp_index)
        nearest = Keyframe.from_pose([*pose[:3, 3], *Rotation.from_matrix(pose[:3, :3]).as_quat()], target.gripper_open,
                                     target.ignore_collisions, target.frame, target.reasons)
        position_error, rotation_error = pose_error(nearest.pose, target)
        if position_error > REACH_SLACK_M or rotation_error > REACH_SLACK_DEG:
            return None
        return nearest

    # --- moving ----------------------------------------------------------------------------------------
    def _path_to(self, result: dict, target: Keyframe) -> tuple[np.ndarray, np.ndarray | None]:
        """(the arm's part [n, J] of an mplib path to the target, with its end moved onto the exact IK
        solution, blended in along the way; that solution, None if IK found none). A correction larger
        than MAX_CORRECTION means another IK branch: the path is left as planned."""
        path = np.asarray(result["position"])[:, : len(self.arm)] if len(result["position"]) else np.zeros((0, len(self.arm)))
        near = self.qpos().astype(np.float64)
        if len(path):
            near[self.arm] = path[-1]
        goal = self.inverse_kinematics(target, near)
        if len(path) and goal is not None and np.abs(goal - path[-1]).max() <= MAX_CORRECTION:
            ramp = (np.arange(1, len(path) + 1) / len(path))[:, None]
            path = path + ramp * (goal - path[-1])
        return path, goal

    def _tcp_along(self, path: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """[n]: where each arm command of the path puts the TCP, along `direction` (forward kinematics)."""
        q = self.qpos().astype(np.float64)
        along = []
        for row in path:
            q[self.arm] = row
            self.planner.pinocchio_model.compute_forward_kinematics(q)
            along.append(self._world_pose(self.tcp_index)[:3, 3] @ direction)
        return np.asarray(along)

    def _follow(self, path: np.ndarray, watch: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
        """Step along the arm path [n, J]; returns (the last joint command, whether a contact stopped it).
        With `watch` (a unit vector), stop where the TCP no longer follows its commands along it
        (`rvt2cli.eval.search`) and hold the arm where it stands."""
        if len(path) == 0:  # already there (e.g. a gripper keyframe where the arm rests)
            return self.qpos()[self.arm], False
        commanded = self._tcp_along(path, watch) if watch is not None else None
        here = asked_before = self._along(watch) if watch is not None else 0.0
        for i, q in enumerate(path):
            self._step(q)
            if watch is None:
                continue
            before, here = here, self._along(watch)
            asked, asked_before = commanded[i] - asked_before, commanded[i]
            if commanded[i] - here > CONTACT_LAG_M and asked > 0 and here - before < CONTACT_SPEED_SHARE * asked:
                hold = self.qpos()[self.arm]
                self._step(hold)
                return hold, True
        return path[-1], False

    def _settle(self, command: np.ndarray) -> None:
        """Hold `command` until the arm rests (at most SETTLE_STEPS)."""
        for _ in range(SETTLE_STEPS):
            if self._at_rest():
                break
            self._step(command)

    def _push(self, target: Keyframe, direction: np.ndarray) -> tuple[np.ndarray, bool] | None:
        """A straight line to the target, through the scene, stopped by a contact along `direction`:
        (the last joint command, whether a contact stopped it), or None when no straight line goes there."""
        result = self._screw(target, use_point_cloud=False)
        return None if result is None else self._follow(self._path_to(result, target)[0], direction)

    def _search_hole(self, target: Keyframe, direction: np.ndarray, command: np.ndarray):
        """The held object rests at a face short of the target: probe across the push for the hole
        (`rvt2cli.eval.search`). Returns (the keyframe to servo onto: the target shifted to where a probe
        went in, or None when none did; the last joint command; the shift in mm). Counts its probes in
        `self.probes`."""
        line = np.asarray(target.position, dtype=np.float64)
        face = self._along(direction)
        depth = float(line @ direction) - face  # from the face to the target, along the push
        plane = across(direction)
        for self.probes, (a, b) in enumerate(self.search.offsets(), start=1):
            shifted = line + a * plane[0] + b * plane[1]
            back = _moved(target, shifted - (depth + self.search.retract_m) * direction)
            retreat = self._screw(back, use_point_cloud=False)
            if retreat is None:
                continue
            command, _ = self._follow(self._path_to(retreat, back)[0])
            probed = self._push(_moved(target, shifted - (depth - PROBE_M) * direction), direction)
            if probed is None:
                continue
            command = probed[0]
            self._settle(command)
            if self._along(direction) - face <= ENTERED_M:
                continue
            inside = _moved(target, shifted)
            pushed = self._push(inside, direction)
            command = pushed[0] if pushed else command
            self._settle(command)
            here = self._along(direction)
            if here - face > INSIDE_M or float(shifted @ direction) - here <= BLOCKED_M:
                return inside, command, 1000.0 * float(np.hypot(a, b))
            # stopped again near the face: the object turned or slid in the fingers, it is not in the hole
        return None, command, None

    def _servo(self, target: Keyframe, command: np.ndarray) -> tuple[np.ndarray, int]:
        """Hold `command` until the arm rests; then, while the TCP rests off the target, shift the command
        by the remaining joint error, until the TCP is within tolerance (or, avoiding collisions, stops
        coming closer).
        Returns (the final command, servo steps spent)."""
        self._settle(command)
        goal = command.copy()
        servo_steps, best, since_best = 0, np.inf, 0
        patience = SERVO_STEPS if target.ignore_collisions else STALL_STEPS
        while servo_steps < SERVO_STEPS and since_best < patience:
            position, rotation = pose_error(self.tcp_pose(), target)
            off = max(position / self.tolerance.position_m, rotation / self.tolerance.rotation_deg)  # 1 = at tolerance
            if off <= 1.0:
                break
            best, since_best = (off, 0) if off < 0.95 * best else (best, since_best + 1)
            if self._at_rest():
                offset = command - goal + (goal - self.qpos()[self.arm])
                command = goal + np.clip(offset, -MAX_SERVO_OFFSET, MAX_SERVO_OFFSET)
            self._step(command)
            servo_steps += 1
        return command, servo_steps

    def _set_gripper(self, open_: bool, hold: np.ndarray) -> None:
        command = 1.0 if open_ else self.gripper_close
        if command != self.gripper:
            self.gripper = command
            for _ in range(GRIPPER_STEPS):
                self._step(hold)

    def _plan_with_fallback(self, target: Keyframe, scene_points: np.ndarray | None):
        """(planner, result, collision fallback used) or None."""
        planned = self.plan(target, scene_points)
        if planned is None and scene_points is not None and not target.ignore_collisions:
            planned = self.plan(target, None)
            return (*planned, True) if planned else None
        return (*planned, False) if planned else None

    def execute(self, target: Keyframe, scene_points: np.ndarray | None = None) -> Reach:
        """Move to the keyframe (or, out of reach, to the nearest pose within REACH_SLACK) and set the
        gripper. An unreachable pose moves nothing. Raises StepBudgetExhausted when the episode's control
        steps run out."""
        self.start_collided = False
        asked, nearest = target, False
        planned = self._plan_with_fallback(target, scene_points)
        if planned is None:
            stand_in = self.nearest_reachable(target)
            if stand_in is None:
                return Reach.unreachable("no_ik", self.start_collided)
            if pose_error(stand_in.pose, target)[0] < 1e-4:  # the target itself is within reach: no way there
                return Reach.unreachable("no_path", self.start_collided)
            target, nearest = stand_in, True
            planned = self._plan_with_fallback(target, scene_points)
            if planned is None:
                return Reach.unreachable("no_path", self.start_collided)
        planner, result, fallback = planned
        self.probes, offset, servo_steps = 0, None, 0
        try:
            path, goal = self._path_to(result, target)
            push = self._insertion_direction(target) if planner == "screw" else None
            command, contact = self._follow(path, push)
            if not len(path) and goal is not None:
                command = goal
            if push is not None:
                self._settle(command)
                if float(np.asarray(target.position) @ push) - self._along(push) > BLOCKED_M:  # at a face, short of it
                    target, command, offset = self._search_hole(target, push, command)
                elif contact:  # stopped near the keyframe: push on to it, as any insertion
                    command = path[-1]
            if target is not None:  # (None: the search found no hole; the object stays at the face)
                command, servo_steps = self._servo(target, command)
            position, rotation = pose_error(self.tcp_pose(), asked)  # where the arm rests, before the gripper acts
            self._set_gripper(asked.gripper_open, command)
        except StepBudgetExhausted:
            position, rotation = pose_error(self.tcp_pose(), asked)
            raise StepBudgetExhausted(Reach(True, position * 1000.0, rotation, planner, fallback, nearest=nearest,
                                            start_in_collision=self.start_collided, probes=self.probes,
                                            interrupted=True)) from None
        return Reach(True, position * 1000.0, rotation, planner, fallback, servo_steps, nearest=nearest,
                     start_in_collision=self.start_collided, probes=self.probes, search_offset_mm=offset)

    def _insertion_direction(self, target: Keyframe) -> np.ndarray | None:
        """The unit direction of the push into `target` if it is an insertion to search for (a keyframe
        that ignores collisions, the gripper holding before and after it, with a search configured), else
        None."""
        if self.search is None or not target.ignore_collisions or target.gripper_open or self.gripper == 1.0:
            return None
        line = np.asarray(target.position) - self.tcp_pose()[:3]
        length = float(np.linalg.norm(line))
        return line / length if length > BLOCKED_M else None


def _moved(keyframe: Keyframe, position: np.ndarray) -> Keyframe:
    """The keyframe at another position."""
    return replace(keyframe, position=tuple(float(v) for v in position))
