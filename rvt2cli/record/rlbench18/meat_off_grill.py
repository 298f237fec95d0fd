"""meat_off_grill: take the named meat (chicken or steak) off the grill and set it down beside it.

RLBench's success: the named meat is on the table next to the grill (a proximity sensor there) and the
gripper holds nothing. The stand-ins: a capsule for the chicken drumstick and a flat box for the steak.
The seed places and turns the grill and decides which half of the grill each meat lies on; the variation
only names the meat.
"""

import numpy as np
import sapien
import torch

from mani_skill.utils.building import actors
from mani_skill.utils.registration import register_env
from mani_skill.utils.structs import Pose

from rvt2cli.record.motions import grasp_from_above, solver, top_down_grasp
from rvt2cli.record.rlbench18.base import VariationEnv

MEATS = ("chicken", "steak")                  # RLBench's order (its variation index)
GRILL_HALF = (0.08, 0.13, 0.04)               # m: the grill's half sizes (x deep, y across, z high)
BARS = 7                                      # the grate's bars, across the grill (visual only)
CHICKEN_RADIUS, CHICKEN_HALF_LENGTH = 0.018, 0.035
STEAK_HALF = (0.045, 0.028, 0.012)
SLOT_Y = 0.065                                # m: each meat lies this far to one side of the grill's middle
GRILL_X = (-0.08, 0.02)
GRILL_Y = (-0.04, 0.08)
GRILL_YAW = np.pi / 8
BESIDE_M = 0.06           # a meat counts as beside the grill once its centre is this far outside the grill...
NEAR_M = 0.25             # ...and no further from the grill's edge than this...
ON_TABLE_M = 0.04         # ...lying on the table (its centre at most this high)
PUT_DOWN_Y = GRILL_HALF[1] + 0.12   # the expert sets the meat down here (grill frame: on the grill's -y side)
LIFT_M = 0.10             # the expert's hand waits, and lifts the meat, this far above the grill's top

GRILL_COLOUR = (0.15, 0.15, 0.16, 1)
BAR_COLOUR = (0.55, 0.55, 0.57, 1)
COLOURS = {"chicken": (0.85, 0.65, 0.35, 1), "steak": (0.55, 0.12, 0.1, 1)}


def _build_grill(scene):
    builder = scene.create_actor_builder()
    builder.add_box_collision(half_size=GRILL_HALF)
    builder.add_box_visual(half_size=GRILL_HALF, material=sapien.render.RenderMaterial(base_color=GRILL_COLOUR))
    bar = sapien.render.RenderMaterial(base_color=BAR_COLOUR)
    for y in np.linspace(-GRILL_HALF[1] + 0.01, GRILL_HALF[1] - 0.01, BARS):
        builder.add_box_visual(pose=sapien.Pose([0, y, GRILL_HALF[2]]), half_size=[GRILL_HALF[0] - 0.005, 0.004, 0.002],
                               material=bar)
    builder.initial_pose = sapien.Pose([0, 0, GRILL_HALF[2]])
    return builder.build_kinematic(name="grill")


def _build_chicken(scene):
    builder = scene.create_actor_builder()
    # grippy and light: a pinched round body of plain material trembles in the hand, and the arm never
    # comes to rest while carrying it (no keyframe where the carry ends)
    builder.add_capsule_collision(radius=CHICKEN_RADIUS, half_length=CHICKEN_HALF_LENGTH, density=100,
                                  material=sapien.physx.PhysxMaterial(static_friction=2.0, dynamic_friction=2.0,
                                                                      restitution=0.0))
    builder.add_capsule_visual(radius=CHICKEN_RADIUS, half_length=CHICKEN_HALF_LENGTH,
                               material=sapien.render.RenderMaterial(base_color=COLOURS["chicken"]))
    builder.initial_pose = sapien.Pose([0, 0.3, CHICKEN_RADIUS])
    return builder.build(name="chicken")


@register_env("RVT2-MeatOffGrill-v1", max_episode_steps=400)
class MeatOffGrillEnv(VariationEnv):
    num_variations = len(MEATS)

    def _build_task(self, options: dict):
        self.grill = _build_grill(self.scene)
        self.meats = (_build_chicken(self.scene),
                      actors.build_box(self.scene, STEAK_HALF, COLOURS["steak"], name="steak",
                                       initial_pose=sapien.Pose([0, -0.3, STEAK_HALF[2]])))

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        x, y, yaw = rng.uniform(*GRILL_X), rng.uniform(*GRILL_Y), rng.uniform(-GRILL_YAW, GRILL_YAW)
        grill = sapien.Pose([x, y, GRILL_HALF[2]], [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])
        self.grill.set_pose(Pose.create(grill))
        sides = (1, -1) if rng.uniform() < 0.5 else (-1, 1)
        for meat, side, half_height in zip(self.meats, sides, (CHICKEN_RADIUS, STEAK_HALF[2])):
            turn = rng.uniform(-np.pi / 8, np.pi / 8)
            shift = rng.uniform(-0.02, 0.02, size=2)
            on_grill = grill * sapien.Pose([shift[0], side * SLOT_Y + shift[1], GRILL_HALF[2] + half_height + 0.001],
                                           [np.cos(turn / 2), 0, 0, np.sin(turn / 2)])
            meat.set_pose(Pose.create(on_grill))

    def beside_grill(self) -> torch.Tensor:
        """Whether each meat lies on the table beside the grill: shape [num_envs, 2], in MEATS's order."""
        beside = []
        for meat in self.meats:
            local = (self.grill.pose.inv() * meat.pose).p
            outside = (local[:, :2].abs() - torch.tensor(GRILL_HALF[:2])).clamp(min=0)   # per axis, beyond the edge
            distance = outside.norm(dim=1)
            beside.append((distance > BESIDE_M) & (distance < NEAR_M) & (meat.pose.p[:, 2] < ON_TABLE_M))
        return torch.stack(beside, dim=1)

    def evaluate(self):
        beside = self.beside_grill()
        held = self.grasped(self.meats)
        named = beside[:, self.variation] & ~held.any(dim=1)
        other = torch.ones_like(beside)
        other[:, self.variation] = False
        moved_other = ((beside | held) & other).any(dim=1)
        return {"success": named, "wrong_object": moved_other & ~named}


def expert(env, seed=None):
    """Grasp the named meat from above, lift it, carry it to the grill's -y side, set it down, let go and
    lift the hand clear."""
    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.75)
    meat = scene.meats[scene.variation]
    grasp = top_down_grasp(scene, meat, at=meat.pose.sp.p)
    grill_top = scene.grill.pose.sp.p[2] + GRILL_HALF[2]
    lifted = sapien.Pose([*grasp.p[:2], grill_top + LIFT_M], grasp.q)
    if not grasp_from_above(planner, grasp, above=lifted) or planner.move_to_pose_with_screw(lifted) == -1:
        return -1
    height = grasp.p[2] - grill_top                 # the grasp's height above what the meat lies on
    down = scene.grill.pose.sp * sapien.Pose([0, -PUT_DOWN_Y, -GRILL_HALF[2]])
    if planner.move_to_pose_with_screw(sapien.Pose([*down.p[:2], grill_top + LIFT_M], grasp.q)) == -1:
        return -1
    if planner.move_to_pose_with_screw(sapien.Pose([*down.p[:2], down.p[2] + height + 0.005], grasp.q)) == -1:
        return -1
    planner.open_gripper()
    return planner.move_to_pose_with_screw(sapien.Pose([*down.p[:2], grill_top + LIFT_M], grasp.q))
