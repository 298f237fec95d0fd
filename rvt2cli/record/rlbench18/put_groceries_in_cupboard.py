"""put_groceries_in_cupboard: put the named grocery item in the cupboard (RLBench, 9 variations).

Nine groceries stand on the table in every episode, each a box or an upright can of its own size and
colour. The cupboard stands on the table to one side of them, raised on a solid base so that its floor is
above the tallest item, its open front facing the robot. RLBench's success: the named item is inside the
cupboard (a proximity sensor there) and the gripper holds nothing; another item inside, or in the hand,
is a wrong object. The seed places and turns everything; the variation only names the item.
"""

from dataclasses import dataclass

import numpy as np
import sapien
import torch

from mani_skill.utils.registration import register_env
from mani_skill.utils.structs import Pose

from rvt2cli.record.rlbench18.base import PANDA_BASE, VariationEnv, build_fixture


@dataclass(frozen=True)
class Grocery:
    name: str
    size: tuple[float, float, float]  # m: a box's length, width and height; a can's diameter, diameter, height
    colour: tuple[float, float, float]
    can: bool = False                 # an upright cylinder, else a box


# RLBench's order (its variation index). Each fits the open gripper across its narrow side.
GROCERIES = (
    Grocery("crackers", (0.09, 0.05, 0.12), (0.95, 0.45, 0.1)),
    Grocery("chocolate jello", (0.07, 0.04, 0.05), (0.4, 0.22, 0.1)),
    Grocery("strawberry jello", (0.07, 0.045, 0.04), (0.95, 0.45, 0.65)),
    Grocery("soup", (0.06, 0.06, 0.09), (0.8, 0.08, 0.08), can=True),
    Grocery("tuna", (0.064, 0.064, 0.035), (0.55, 0.72, 0.92), can=True),
    Grocery("spam", (0.08, 0.045, 0.06), (0.12, 0.2, 0.55)),
    Grocery("coffee", (0.066, 0.066, 0.11), (0.12, 0.1, 0.08), can=True),
    Grocery("mustard", (0.05, 0.035, 0.12), (0.95, 0.85, 0.1)),
    Grocery("sugar", (0.08, 0.04, 0.1), (0.93, 0.93, 0.9)),
)
TALLEST = max(g.size[2] for g in GROCERIES)
DENSITY = 200  # kg/m^3: light packaging; a heavy box slips out of fingers holding it by its top
GRIPPY = dict(static_friction=1.5, dynamic_friction=1.5, restitution=0.0)

# The cupboard's frame: origin on the table under the middle of its open front, x into it, z up.
WIDTH, DEPTH = 0.32, 0.17        # m: outer size across (y) and deep (x)
WALL = 0.01
FLOOR = TALLEST + 0.02           # m: the top of its floor, so an item carried level just above it clears the others
ROOF = 0.58                      # m: the underside of its roof, above the wrist of a hand holding the tallest item inside
CUPBOARD_COLOUR = (0.55, 0.42, 0.3, 1)

# The layout, for a cupboard on the left (+y); on the right, y is mirrored. The cupboard's front stands
# CUPBOARD_RANGE from the robot's base, facing it; the items stand on a 3 x 3 grid of spots (shuffled,
# jittered) beside it, each turned at most ITEM_YAW from pointing at the robot, so that the hand closing
# across any of them stays clear of its neighbours.
CUPBOARD_RANGE = (0.6, 0.63)      # m, from the base
CUPBOARD_BEARING = (0.45, 0.55)   # rad, from the robot's forward direction
CUPBOARD_YAW = 0.1                # rad: turned at most this much from facing the base
SPOT_X = (-0.32, -0.18, -0.04)
SPOT_Y = (-0.26, -0.07, 0.12)
JITTER = 0.015
ITEM_YAW = np.pi / 6


def _yaw(angle: float) -> list[float]:
    return [np.cos(angle / 2), 0, 0, np.sin(angle / 2)]


def _build_cupboard(scene):
    w, d = WIDTH / 2, DEPTH / 2
    top = ROOF + WALL
    boxes = [([d, 0, FLOOR / 2], [d, w, FLOOR / 2]),                      # the base, its top the floor
             ([DEPTH - WALL / 2, 0, top / 2], [WALL / 2, w, top / 2])]    # the back
    boxes += [([d, side * (w - WALL / 2), top / 2], [d, WALL / 2, top / 2]) for side in (-1, 1)]
    boxes.append(([d, 0, ROOF + WALL / 2], [d, w, WALL / 2]))              # the roof
    return build_fixture(scene, boxes, CUPBOARD_COLOUR, "cupboard", at=(0.3, 0, 0))


def _build_grocery(scene, grocery: Grocery, x: float):
    builder = scene.create_actor_builder()
    material = sapien.render.RenderMaterial(base_color=[*grocery.colour, 1])
    physics = sapien.physx.PhysxMaterial(**GRIPPY)
    length, width, height = grocery.size
    if grocery.can:
        upright = sapien.Pose(q=[np.cos(np.pi / 4), 0, -np.sin(np.pi / 4), 0])  # a SAPIEN cylinder lies along x
        builder.add_cylinder_collision(upright, radius=length / 2, half_length=height / 2, material=physics, density=DENSITY)
        builder.add_cylinder_visual(upright, radius=length / 2, half_length=height / 2, material=material)
    else:
        half = [length / 2, width / 2, height / 2]
        builder.add_box_collision(half_size=half, material=physics, density=DENSITY)
        builder.add_box_visual(half_size=half, material=material)
    builder.initial_pose = sapien.Pose([x, 0.6, height / 2])
    return builder.build(name=grocery.name.replace(" ", "_"))


@register_env("RVT2-PutGroceriesInCupboard-v1", max_episode_steps=400)
class PutGroceriesInCupboardEnv(VariationEnv):
    """The named item's centre is inside the cupboard (between its walls, above its floor, below its
    roof) and the gripper holds nothing."""

    num_variations = len(GROCERIES)

    def _build_task(self, options: dict):
        self.cupboard = _build_cupboard(self.scene)
        self.groceries = [_build_grocery(self.scene, g, 0.1 * i) for i, g in enumerate(GROCERIES)]

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        side = rng.choice([-1.0, 1.0])
        distance, bearing = rng.uniform(*CUPBOARD_RANGE), side * rng.uniform(*CUPBOARD_BEARING)
        front = np.array(PANDA_BASE[:2]) + distance * np.array([np.cos(bearing), np.sin(bearing)])
        facing = bearing + rng.uniform(-CUPBOARD_YAW, CUPBOARD_YAW)
        self.cupboard.set_pose(Pose.create(sapien.Pose([*front, 0], _yaw(facing))))
        spots = [(x, side * y) for x in SPOT_X for y in SPOT_Y]
        for grocery, actor, spot in zip(GROCERIES, self.groceries, rng.permutation(len(spots))):
            xy = np.array(spots[spot]) + rng.uniform(-JITTER, JITTER, size=2)
            actor.set_pose(Pose.create(sapien.Pose([*xy, grocery.size[2] / 2], _yaw(rng.uniform(-ITEM_YAW, ITEM_YAW)))))

    def in_cupboard_frame(self, point) -> sapien.Pose:
        return self.cupboard.pose.sp * sapien.Pose(point)

    def inside(self) -> torch.Tensor:
        """Whether each item's centre is inside the cupboard: shape [num_envs, 9], GROCERIES's order."""
        inside = []
        for actor in self.groceries:
            local = (self.cupboard.pose.inv() * actor.pose).p
            inside.append((local[:, 0] > 0) & (local[:, 0] < DEPTH - WALL) & (local[:, 1].abs() < WIDTH / 2 - WALL)
                          & (local[:, 2] > FLOOR) & (local[:, 2] < ROOF))
        return torch.stack(inside, dim=1)

    def evaluate(self):
        inside = self.inside()
        held = self.grasped(self.groceries)
        named = torch.arange(len(GROCERIES), device=inside.device) == self.variation
        return {"success": inside[:, self.variation] & ~held.any(dim=1),
                "wrong_object": ((inside | held) & ~named).any(dim=1)}


GRIP_DEPTH = 0.025   # m: the fingers close this far below an item's top (no lower than its middle)
CARRY_M = 0.01       # the item's bottom is carried this far above the cupboard's floor...
BEFORE_M = 0.04      # ...to this far before its front, and let go inside, its centre this far in
INSIDE_M = 0.09


def _closing(scene, across: np.ndarray) -> np.ndarray:
    """`across` or its opposite, whichever the open hand is nearer to closing along now (the smaller turn)."""
    now = scene.agent.tcp.pose.to_transformation_matrix()[0, :3, 1].cpu().numpy()
    return across if across @ now >= 0 else -across


def expert(env, seed=None):
    """Grasp the named item from above, across its narrow side; lift it level with the cupboard's floor;
    carry it, turned to go in lengthways, before the cupboard, then straight in; let go and back out the
    same way. -1 if a motion cannot be planned."""
    from rvt2cli.record.motions import grasp_from_above, solver

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.75)
    grocery, actor = GROCERIES[scene.variation], scene.groceries[scene.variation]
    cupboard = scene.cupboard.pose.sp.to_transformation_matrix()[:3, :3]
    down = np.array([0, 0, -1.0])

    item = actor.pose.sp
    across = cupboard[:, 1] if grocery.can else item.to_transformation_matrix()[:3, 1]
    height = grocery.size[2]
    point = item.p + [0, 0, max(height / 2 - GRIP_DEPTH, 0.0)]
    grasp = scene.agent.build_grasp_pose(down, _closing(scene, across), point)
    if not grasp_from_above(planner, grasp):
        return -1
    bottom = item.p[2] - height / 2
    lifted = sapien.Pose(grasp.p + [0, 0, FLOOR + CARRY_M - bottom], grasp.q)
    if planner.move_to_pose_with_screw(lifted) == -1:
        return -1

    # the hand turned to close across the cupboard, placed so that the item, as it hangs in the hand, is
    # centred at a point given in the cupboard's frame
    held = scene.agent.tcp.pose.sp.inv() * actor.pose.sp
    turned = scene.agent.build_grasp_pose(down, _closing(scene, cupboard[:, 1]), np.zeros(3)).q

    def carrying_to(point) -> sapien.Pose:
        goal = scene.in_cupboard_frame(point).p
        hand = sapien.Pose(np.zeros(3), turned)
        return sapien.Pose(goal - (hand * held).p, turned)

    middle = FLOOR + CARRY_M + height / 2
    before = carrying_to([-BEFORE_M - grocery.size[0] / 2, 0, middle])
    if planner.move_to_pose_with_screw(before) == -1:
        return -1
    if planner.move_to_pose_with_screw(carrying_to([INSIDE_M, 0, middle])) == -1:
        return -1
    planner.open_gripper()
    return planner.move_to_pose_with_screw(before)
