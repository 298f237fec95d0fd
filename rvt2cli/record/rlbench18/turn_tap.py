"""turn_tap: turn the left or the right handle of a tap a quarter turn.

RLBench's variations (`rlbench/tasks/turn_tap.py`): the handle, left or right. Success: that handle's joint
turned 1.57 rad from where it started (RLBench's joint condition, either way round).

Here the tap is a block with a spout and two lever handles on vertical hinges, facing the robot; left and
right are as the robot sees them (left: +y, the tap turned at most 30 degrees). The hinges hold a handle
where it is left by friction.
"""

import numpy as np
import sapien
import torch
from transforms3d.euler import euler2quat

from mani_skill.utils.registration import register_env

from rvt2cli.record.rlbench18.base import VariationEnv

SIDES = ("left", "right")
SIDE_Y = {"left": 1.0, "right": -1.0}   # the handles' side along the tap's y (the robot's left is +y)
TURNED_RAD = 1.57                        # RLBench's condition
BODY_HALF = (0.03, 0.11, 0.02)           # m: the tap's block, on the table
HANDLE_Y = 0.075                         # m from the middle to each hinge
STEM_RADIUS, STEM_HALF = 0.012, 0.015    # the handle's stem on the block...
LEVER_HALF = (0.01, 0.045, 0.012)        # ...and its lever on top, along the tap's y at the start
HINGE_FRICTION, HINGE_DAMPING = 0.2, 0.5
TAP_X, TAP_Y, TAP_YAW = (0.0, 0.1), (-0.1, 0.1), np.radians(30.0)
METAL = [0.75, 0.75, 0.78, 1.0]
HANDLE_RGBA = {"left": [0.85, 0.2, 0.2, 1.0], "right": [0.2, 0.35, 0.85, 1.0]}  # hot and cold, as taps are marked
# the revolute joint turns about its frame's x axis: turn it to point up
X_TO_UP = sapien.Pose(q=[np.sqrt(0.5), 0, -np.sqrt(0.5), 0])


@register_env("RVT2-TurnTap-v1", max_episode_steps=300)
class TurnTapEnv(VariationEnv):
    num_variations = len(SIDES)

    def _build_task(self, options: dict):
        builder = self.scene.create_articulation_builder()
        body = builder.create_link_builder()
        body.set_name("tap_body")
        metal = sapien.render.RenderMaterial(base_color=METAL)
        neck_half = 0.035
        parts = [  # (pose, half size) boxes: the block, the spout's neck, the spout reaching towards the robot
            (sapien.Pose([0, 0, BODY_HALF[2]]), BODY_HALF),
            (sapien.Pose([0, 0, 2 * BODY_HALF[2] + neck_half]), [0.012, 0.012, neck_half]),
            (sapien.Pose([-0.035, 0, 2 * BODY_HALF[2] + 2 * neck_half - 0.01]), [0.045, 0.01, 0.01]),
        ]
        for pose, half in parts:
            body.add_box_collision(pose, half)
            body.add_box_visual(pose, half, material=metal)
        self.handle_joints = {}
        for side in SIDES:
            handle = builder.create_link_builder(body)
            handle.set_name(f"{side}_handle")
            handle.set_joint_name(f"{side}_joint")
            material = sapien.render.RenderMaterial(base_color=HANDLE_RGBA[side])
            upright = sapien.Pose(q=[np.sqrt(0.5), 0, np.sqrt(0.5), 0])  # the cylinder's axis (x) turned up
            stem = sapien.Pose([0, 0, STEM_HALF]) * upright
            lever = sapien.Pose([0, 0, 2 * STEM_HALF + LEVER_HALF[2]])
            handle.add_cylinder_collision(stem, STEM_RADIUS, STEM_HALF)
            handle.add_cylinder_visual(stem, STEM_RADIUS, STEM_HALF, material=metal)
            handle.add_box_collision(lever, LEVER_HALF)
            handle.add_box_visual(lever, LEVER_HALF, material=material)
            hinge = sapien.Pose([0, SIDE_Y[side] * HANDLE_Y, 2 * BODY_HALF[2]])
            handle.set_joint_properties("revolute", limits=[[-np.pi, np.pi]], pose_in_parent=hinge * X_TO_UP,
                                        pose_in_child=X_TO_UP, friction=HINGE_FRICTION, damping=HINGE_DAMPING)
        builder.set_initial_pose(sapien.Pose())
        self.tap = builder.build(name="tap", fix_root_link=True)

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        yaw = rng.uniform(-TAP_YAW, TAP_YAW)
        self.tap.set_pose(sapien.Pose([rng.uniform(*TAP_X), rng.uniform(*TAP_Y), 0], euler2quat(0, 0, yaw)))
        self.tap.set_qpos(torch.zeros((1, len(SIDES))))
        self.tap.set_qvel(torch.zeros((1, len(SIDES))))

    def handle_angles(self) -> dict[str, float]:
        """How far each handle is turned from where it started (rad)."""
        qpos = self.tap.get_qpos()[0]
        return {j.name.split("_")[0]: float(qpos[i]) for i, j in enumerate(self.tap.get_active_joints())}

    def lever_pose(self, side: str) -> sapien.Pose:
        """The pose of a handle's lever (its middle, on the hinge's axis)."""
        link = self.tap.links_map[f"{side}_handle"]
        return link.pose.sp * sapien.Pose([0, 0, 2 * STEM_HALF + LEVER_HALF[2]])

    def evaluate(self):
        angles = self.handle_angles()
        named, other = SIDES[self.variation], SIDES[1 - self.variation]
        return {"success": torch.tensor([abs(angles[named]) >= TURNED_RAD]),
                "wrong_object": torch.tensor([abs(angles[other]) >= TURNED_RAD])}


TURN_RAD = np.radians(100.0)  # a quarter turn and a little more: the fingers give a few degrees
ABOVE_M = 0.08


def _quickest(planner, poses):
    """Of these poses, the one the planner reaches in the fewest control steps from where the arm stands (None:
    it reaches none). Either way round a lever can look alike, but not to the wrist: one way may leave it too
    little room, or a path the planner times at a crawl."""
    plans = [(len(plan["position"]), i) for i, plan in enumerate(planner.move_to_pose_with_screw(p, dry_run=True) for p in poses)
             if not (isinstance(plan, int) and plan == -1)]
    return poses[min(plans)[1]] if plans else None


def expert(env, seed=None):
    """Grasp the named handle's lever over its hinge from above, turn it a quarter turn (whichever way the
    wrist turns it quicker), let go and back off upwards. Returns -1 when a motion cannot be planned."""
    from rvt2cli.record.motions import solver

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.9)
    lever = scene.lever_pose(SIDES[scene.variation])
    across = lever.to_transformation_matrix()[:3, 0]  # the lever runs along its y: the fingers close along its x
    grasps = [scene.agent.build_grasp_pose(np.array([0.0, 0.0, -1.0]), closing, lever.p) for closing in (across, -across)]
    above = _quickest(planner, [sapien.Pose(g.p + [0, 0, ABOVE_M], g.q) for g in grasps])
    if above is None or planner.move_to_pose_with_screw(above) == -1:
        return -1
    grasp = sapien.Pose(lever.p, above.q)
    if planner.move_to_pose_with_screw(grasp, refine_steps=0) == -1:  # the arrival and the grasp: one keyframe
        return -1
    planner.close_gripper()
    turned = _quickest(planner, [grasp * sapien.Pose(q=euler2quat(0, 0, way * TURN_RAD)) for way in (1.0, -1.0)])
    if turned is None or planner.move_to_pose_with_screw(turned) == -1:
        return -1
    planner.open_gripper()
    return planner.move_to_pose_with_screw(sapien.Pose(turned.p + [0, 0, ABOVE_M], turned.q))
