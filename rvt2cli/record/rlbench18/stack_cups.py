"""stack_cups: stack the other two cups into the cup of the named colour (RLBench's 20 variations: one per
colour).

Three identical tapered cups stand upright, unturned (as RLBench's); the first wears the instruction's
colour, the other two colours drawn from the seed (each another colour, as in RLBench). The seed alone
places them. A cup is a round bottom and twelve tilted walls, so that one drops into another.
Success: both other cups stand inside the named one and the gripper holds nothing.
"""

import numpy as np
import sapien
import torch

from mani_skill.utils.registration import register_env

from rvt2cli.record.motions import DROP_M, pick_and_place, solver
from rvt2cli.record.rlbench18.base import VariationEnv
from rvt2cli.record.rlbench18.colors import COLORS, other_color, rgba
from rvt2cli.record.rlbench18.layout import scatter

BOTTOM_RADIUS, TOP_RADIUS, HEIGHT = 0.025, 0.035, 0.06  # m, at the middle of the wall
WALL, SIDES = 0.004, 12
SLOPE = (TOP_RADIUS - BOTTOM_RADIUS) / HEIGHT
TILT = np.arctan(SLOPE)
# m: how much higher a cup rests inside another (measured: the walls' corners stick out where the cup narrows)
NEST = 0.031
INSIDE_XY = 0.015  # m: a cup is in the stack when its axis is this near the named cup's...
REGION = ((-0.2, -0.25), (0.1, 0.25))  # m: where the cups stand
SPACING = 0.15  # m between cups: the gripper's outer finger passes outside a neighbour
GRIP_BELOW_RIM = 0.008  # m: the fingers pinch the wall this far below the rim
RELEASE_ABOVE = 0.01    # m: a cup is let go this far above its nest, and drops in
# m: a carried cup's bottom passes this far over the stack's rim. Low, so that the lowering is short: the
# executor plans it around the scene as the cameras last saw it, where the held cup's bottom still lies
# 5 cm under the inner finger; a longer lowering meets that stale bottom, and a detour knocks the stack.
CARRY_CLEARANCE = 0.02

_UPRIGHT = [np.cos(np.pi / 4), 0, -np.sin(np.pi / 4), 0]  # a SAPIEN cylinder's axis is x: turn it to z


def _yaw(angle: float) -> list[float]:
    return [np.cos(angle / 2), 0, 0, np.sin(angle / 2)]


def build_cup(scene, color, name):
    builder = scene.create_actor_builder()
    material = sapien.render.RenderMaterial(base_color=color)
    bottom = sapien.Pose([0, 0, WALL / 2], _UPRIGHT)
    builder.add_cylinder_collision(bottom, radius=BOTTOM_RADIUS, half_length=WALL / 2)
    builder.add_cylinder_visual(bottom, radius=BOTTOM_RADIUS, half_length=WALL / 2, material=material)
    half = [WALL / 2, TOP_RADIUS * np.tan(np.pi / SIDES), HEIGHT / np.cos(TILT) / 2]  # wide enough at the rim
    middle = (BOTTOM_RADIUS + TOP_RADIUS) / 2
    for k in range(SIDES):
        angle = 2 * np.pi * k / SIDES
        tilted_out = sapien.Pose(q=_yaw(angle)) * sapien.Pose(q=[np.cos(TILT / 2), 0, np.sin(TILT / 2), 0])
        pose = sapien.Pose([middle * np.cos(angle), middle * np.sin(angle), HEIGHT / 2], tilted_out.q)
        builder.add_box_collision(pose, half_size=half)
        builder.add_box_visual(pose, half_size=half, material=material)
    builder.initial_pose = sapien.Pose([0.5, 0, 0])
    return builder.build(name=name)


@register_env("RVT2-StackCups-v1", max_episode_steps=600)
class StackCupsEnv(VariationEnv):
    num_variations = len(COLORS)

    def _build_task(self, options):
        rng = self._episode_rng
        self.cup_colors = [self.variation, other_color(rng, self.variation), other_color(rng, self.variation)]
        self.cups = [build_cup(self.scene, rgba(c), f"cup_{i}") for i, c in enumerate(self.cup_colors)]

    def _place_task(self, env_idx, options):
        for cup, xy in zip(self.cups, scatter(self._episode_rng, len(self.cups), *REGION, spacing=SPACING)):
            cup.set_pose(sapien.Pose([*xy, 0]))

    @property
    def base_cups(self) -> list:
        """The cups wearing the instruction's colour (by the colours the scene was built with: after a
        change of variation, the cups that the new instruction names, if any)."""
        return [cup for cup, c in zip(self.cups, self.cup_colors) if c == self.variation]

    def _inside(self, cup, base) -> torch.Tensor:
        offset = cup.pose.p - base.pose.p
        # ...and its bottom lies inside the named cup, or inside the cup nested in it
        near_axis = torch.linalg.norm(offset[:, :2], dim=1) <= INSIDE_XY
        return near_axis & (offset[:, 2] > 0) & (offset[:, 2] < HEIGHT + NEST)

    def evaluate(self):
        # RLBench's: both other cups inside the named one; inside a cup of another colour is the wrong target
        bases = torch.stack([torch.stack([self._inside(cup, base) for cup in self.cups if cup is not base]).all(dim=0)
                             for base in self.cups])  # [cups, envs]
        named = torch.tensor([c == self.variation for c in self.cup_colors])[:, None]
        held = self.grasped(self.cups).any(dim=1)
        return {"success": (bases & named).any(dim=0) & ~held, "wrong_target": (bases & ~named).any(dim=0) & ~held}


def _rim_grasp(scene, cup):
    """The TCP pose that pinches the cup's wall GRIP_BELOW_RIM under the rim, on the side facing the
    table's middle line (y = 0), the fingers closing across the wall."""
    centre = cup.pose.sp.p
    outward = np.array([0.0, -1.0 if centre[1] > 0 else 1.0, 0.0])
    height = HEIGHT - GRIP_BELOW_RIM
    point = centre + outward * (BOTTOM_RADIUS + SLOPE * height) + [0, 0, height]
    hand = scene.agent.tcp.pose.to_transformation_matrix()[0, :3, 1].cpu().numpy()  # the way the fingers close now
    closing = outward if outward @ hand >= 0 else -outward  # either way round: the nearer turn of the hand
    return scene.agent.build_grasp_pose(np.array([0, 0, -1.0]), closing, point)


def expert(env, seed=None):
    """Pinch each other cup's wall (the nearest first), carry it over the named cup, and let it drop in.
    Returns -1 when a motion cannot be planned."""

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.9)
    base = scene.base_cups[0]
    others = sorted((c for c in scene.cups if c is not base),
                    key=lambda c: np.linalg.norm(c.pose.sp.p[:2] - base.pose.sp.p[:2]))
    result = -1
    for level, cup in enumerate(others, start=1):
        under = base.pose.sp.p
        goal = [under[0], under[1], under[2] + level * NEST + RELEASE_ABOVE - DROP_M]  # pick_and_place adds DROP_M
        rim = under[2] + HEIGHT + (level - 1) * NEST  # the stack's rim, m
        result = pick_and_place(planner, scene, cup, goal, carry_z=rim + CARRY_CLEARANCE, grasp=_rim_grasp(scene, cup))
        if result == -1:
            return -1
    return result
