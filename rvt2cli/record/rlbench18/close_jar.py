"""close_jar: put the lid on the jar of the named colour (RLBench's 20 variations: one per colour).

Two jars stand on the table, one wearing the instruction's colour and one another colour drawn from the
seed; which of the two wears it follows the variation's parity, as in RLBench. The lid lies upright on
the table. It is placed, not screwed: a cap whose skirt drops over the jar's neck with 6 mm to spare.
Success: the lid sits on the named jar's neck and the gripper holds nothing.
"""

import numpy as np
import sapien
import torch

from mani_skill.utils.registration import register_env

from rvt2cli.record.motions import pick_and_place, solver
from rvt2cli.record.rlbench18.base import VariationEnv
from rvt2cli.record.rlbench18.colors import COLORS, other_color, rgba
from rvt2cli.record.rlbench18.layout import scatter

BODY_RADIUS, BODY_HEIGHT = 0.035, 0.07  # m: the jar, a cylinder standing on the table...
NECK_RADIUS, NECK_HEIGHT = 0.02, 0.02   # ...with a narrower neck on top
CAP_RADIUS, CAP_THICKNESS = 0.03, 0.01  # m: the lid's top disc...
SKIRT_INNER, SKIRT_WALL, SKIRT_HEIGHT, SKIRT_SIDES = 0.026, 0.004, 0.018, 8  # ...and the skirt under its rim
LID_COLOR = [0.85, 0.75, 0.6, 1.0]  # beige: no colour an instruction names
CLOSED_Z = BODY_HEIGHT + NECK_HEIGHT - SKIRT_HEIGHT  # m: the lid's origin (its skirt's bottom) on a jar
SEATED_XY, SEATED_Z = 0.01, 0.01  # m: how near the lid must be to its place on the neck
REGION = ((-0.22, -0.25), (0.1, 0.25))  # m: where the jars and the lid stand
SPACING = 0.13  # m between their centres: the open gripper passes between them
CARRY_CLEARANCE = 0.05  # m: the carried lid's bottom passes this far over the jars' necks

_UPRIGHT = [np.cos(np.pi / 4), 0, -np.sin(np.pi / 4), 0]  # a SAPIEN cylinder's axis is x: turn it to z


def _build_jar(scene, color, name):
    builder = scene.create_actor_builder()
    material = sapien.render.RenderMaterial(base_color=color)
    for radius, bottom, height in ((BODY_RADIUS, 0.0, BODY_HEIGHT), (NECK_RADIUS, BODY_HEIGHT, NECK_HEIGHT)):
        pose = sapien.Pose([0, 0, bottom + height / 2], _UPRIGHT)
        builder.add_cylinder_collision(pose, radius=radius, half_length=height / 2)
        builder.add_cylinder_visual(pose, radius=radius, half_length=height / 2, material=material)
    builder.initial_pose = sapien.Pose([0.5, 0, 0])
    return builder.build_kinematic(name=name)


def _build_lid(scene, name):
    builder = scene.create_actor_builder()
    material = sapien.render.RenderMaterial(base_color=LID_COLOR)
    disc = sapien.Pose([0, 0, SKIRT_HEIGHT + CAP_THICKNESS / 2], _UPRIGHT)
    builder.add_cylinder_collision(disc, radius=CAP_RADIUS, half_length=CAP_THICKNESS / 2)
    builder.add_cylinder_visual(disc, radius=CAP_RADIUS, half_length=CAP_THICKNESS / 2, material=material)
    middle = SKIRT_INNER + SKIRT_WALL / 2
    side = 2 * (SKIRT_INNER + SKIRT_WALL) * np.tan(np.pi / SKIRT_SIDES)  # the walls meet at the outer corners
    for k in range(SKIRT_SIDES):
        angle = 2 * np.pi * k / SKIRT_SIDES
        pose = sapien.Pose([middle * np.cos(angle), middle * np.sin(angle), SKIRT_HEIGHT / 2],
                           [np.cos(angle / 2), 0, 0, np.sin(angle / 2)])
        half = [SKIRT_WALL / 2, side / 2, SKIRT_HEIGHT / 2]
        builder.add_box_collision(pose, half_size=half)
        builder.add_box_visual(pose, half_size=half, material=material)
    builder.initial_pose = sapien.Pose([0.5, 0.3, 0])
    return builder.build(name=name)


@register_env("RVT2-CloseJar-v1", max_episode_steps=400)
class CloseJarEnv(VariationEnv):
    num_variations = len(COLORS)

    def _build_task(self, options):
        other = other_color(self._episode_rng, self.variation)
        self.jar_colors = [other, other]
        self.jar_colors[self.variation % 2] = self.variation
        self.jars = [_build_jar(self.scene, rgba(c), f"jar_{i}") for i, c in enumerate(self.jar_colors)]
        self.lid = _build_lid(self.scene, "lid")

    @property
    def target_jars(self) -> list:
        """The jars wearing the instruction's colour (by the colours the scene was built with: after a
        change of variation, the jars that the new instruction names, if any)."""
        return [j for j, c in zip(self.jars, self.jar_colors) if c == self.variation]

    def _place_task(self, env_idx, options):
        jar_0, jar_1, lid = scatter(self._episode_rng, 3, *REGION, spacing=SPACING)
        yaw = self._episode_rng.uniform(0, 2 * np.pi / SKIRT_SIDES)
        self.jars[0].set_pose(sapien.Pose([*jar_0, 0]))
        self.jars[1].set_pose(sapien.Pose([*jar_1, 0]))
        self.lid.set_pose(sapien.Pose([*lid, 0], [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]))

    def _closes(self, jar) -> torch.Tensor:
        offset = self.lid.pose.p - jar.pose.p
        return (torch.linalg.norm(offset[:, :2], dim=1) <= SEATED_XY) & ((offset[:, 2] - CLOSED_Z).abs() <= SEATED_Z)

    def evaluate(self):
        held = self.grasped([self.lid])[:, 0]
        named = [self._closes(j) & (c == self.variation) for j, c in zip(self.jars, self.jar_colors)]
        other = [self._closes(j) & (c != self.variation) for j, c in zip(self.jars, self.jar_colors)]
        return {"success": torch.stack(named).any(dim=0) & ~held, "wrong_target": torch.stack(other).any(dim=0) & ~held}


def expert(env, seed=None):
    """Grasp the lid by its rim, carry it over the named jar, lower it onto the neck and let go.
    Returns -1 when a motion cannot be planned."""

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.9)
    jar = scene.target_jars[0].pose.sp.p
    return pick_and_place(planner, scene, scene.lid, [jar[0], jar[1], CLOSED_Z],
                          carry_z=BODY_HEIGHT + NECK_HEIGHT + CARRY_CLEARANCE)
