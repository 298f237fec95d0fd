"""place_cups: put 1, 2 or 3 cups on the cup holder (RLBench's 3 variations).

The holder is a board with three upright pegs in a row; three identical cups stand mouth-down on the
table, and a cup is on the holder when it stands mouth-down on the board over a peg. (RLBench hangs mugs
by their handles on a mug tree's spokes; ours go over upright pegs, as on a drying rack.) The seed alone
places the holder and the cups; the variation is the number the instruction asks.
Success: exactly that many cups stand over pegs, and the gripper holds nothing.
"""

import numpy as np
import sapien
import torch

from mani_skill.utils.registration import register_env

from rvt2cli.record.motions import pick_and_place, solver, top_down_grasp
from rvt2cli.record.rlbench18.base import VariationEnv
from rvt2cli.record.rlbench18.layout import scatter
from rvt2cli.record.rlbench18.stack_cups import HEIGHT, build_cup

CUP_COLOR = [0.8, 0.8, 0.9, 1.0]  # pale grey-blue, the same for every cup: the instruction counts them
HOLDER_COLOR = [0.35, 0.25, 0.2, 1.0]
BOARD_HALF = (0.05, 0.16, 0.005)  # m: the holder's board, long along the row of pegs
PEG_RADIUS, PEG_HEIGHT, PEG_PITCH = 0.008, 0.045, 0.105  # m: the pegs stand on the board, PEG_PITCH apart
BOARD_TOP = 2 * BOARD_HALF[2]
PEG_OFFSETS = (-PEG_PITCH, 0.0, PEG_PITCH)  # m, along the board
HOLDER_REGION = ((0.0, -0.08), (0.08, 0.08))  # m: the holder's centre (its row of pegs runs along y)
CUP_REGION = ((-0.24, -0.26), (-0.09, 0.26))  # m: the cups, between the robot and the holder
CUP_SPACING = 0.12
ON_PEG_XY = 0.02     # m: a cup is over a peg when its axis is this near the peg's...
ON_BOARD_Z = 0.01    # ...and its mouth this near the board's top
CARRY_CLEARANCE = 0.04  # m: a carried cup's mouth passes this far over the pegs
GRIP_BELOW_TOP = 0.012  # m: the fingers close this far under an upturned cup's top, where it is narrow

_UPRIGHT = [np.cos(np.pi / 4), 0, -np.sin(np.pi / 4), 0]  # a SAPIEN cylinder's axis is x: turn it to z
_MOUTH_DOWN = [0.0, 1.0, 0.0, 0.0]  # half a turn about x: the cup's origin (its bottom's centre) on top


def _build_holder(scene, name):
    builder = scene.create_actor_builder()
    material = sapien.render.RenderMaterial(base_color=HOLDER_COLOR)
    board = sapien.Pose([0, 0, BOARD_HALF[2]])
    builder.add_box_collision(board, half_size=BOARD_HALF)
    builder.add_box_visual(board, half_size=BOARD_HALF, material=material)
    for y in PEG_OFFSETS:
        peg = sapien.Pose([0, y, BOARD_TOP + PEG_HEIGHT / 2], _UPRIGHT)
        builder.add_cylinder_collision(peg, radius=PEG_RADIUS, half_length=PEG_HEIGHT / 2)
        builder.add_cylinder_visual(peg, radius=PEG_RADIUS, half_length=PEG_HEIGHT / 2, material=material)
    builder.initial_pose = sapien.Pose([0.5, 0, 0])
    return builder.build_kinematic(name=name)


@register_env("RVT2-PlaceCups-v1", max_episode_steps=600)
class PlaceCupsEnv(VariationEnv):
    num_variations = 3

    @property
    def count(self) -> int:
        return self.variation + 1

    def _build_task(self, options):
        self.holder = _build_holder(self.scene, "cup_holder")
        self.cups = [build_cup(self.scene, CUP_COLOR, f"cup_{i}") for i in range(3)]

    def _place_task(self, env_idx, options):
        rng = self._episode_rng
        holder = scatter(rng, 1, *HOLDER_REGION, spacing=0)[0]
        self.holder.set_pose(sapien.Pose([*holder, 0]))
        for cup, xy in zip(self.cups, scatter(rng, len(self.cups), *CUP_REGION, spacing=CUP_SPACING)):
            cup.set_pose(sapien.Pose([*xy, HEIGHT], _MOUTH_DOWN))

    def pegs(self) -> np.ndarray:
        """The pegs' xy (world, m)."""
        centre = self.holder.pose.sp.p
        return np.array([[centre[0], centre[1] + y] for y in PEG_OFFSETS])

    def _over_a_peg(self, cup) -> torch.Tensor:
        pegs = torch.as_tensor(self.pegs(), dtype=cup.pose.p.dtype)
        near = torch.cdist(cup.pose.p[:, :2], pegs).min(dim=1).values <= ON_PEG_XY
        mouth = cup.pose.p[:, 2] - HEIGHT
        return near & ((mouth - (self.holder.pose.p[:, 2] + BOARD_TOP)).abs() <= ON_BOARD_Z)

    def evaluate(self):
        placed = torch.stack([self._over_a_peg(cup) for cup in self.cups]).sum(dim=0)
        held = self.grasped(self.cups).any(dim=1)
        return {"success": (placed == self.count) & ~held, "placed": placed}


def expert(env, seed=None):
    """Take the cups nearest the holder first and put each mouth-down over the next free peg (the nearest
    peg first). Returns -1 when a motion cannot be planned."""

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.9)
    holder = scene.holder.pose.sp.p
    cups = sorted(scene.cups, key=lambda c: np.linalg.norm(c.pose.sp.p[:2] - holder[:2]))[:scene.count]
    free = list(scene.pegs())
    result = -1
    for cup in cups:
        peg = min(free, key=lambda p: np.linalg.norm(p - cup.pose.sp.p[:2]))
        free = [p for p in free if p is not peg]
        top = BOARD_TOP + holder[2] + HEIGHT  # the cup's origin (its bottom, upturned) once it stands on the board
        grasp = top_down_grasp(scene, cup, at=cup.pose.sp.p - [0, 0, GRIP_BELOW_TOP])
        result = pick_and_place(planner, scene, cup, [*peg, top], carry_z=top + PEG_HEIGHT + CARRY_CLEARANCE,
                                grasp=grasp)
        if result == -1:
            return -1
    return result
