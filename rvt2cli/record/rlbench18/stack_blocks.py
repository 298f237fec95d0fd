"""stack_blocks: stack 2, 3 or 4 blocks of the named colour on the square target (RLBench's 60 variations:
20 colours x 3 heights).

Four blocks wear the instruction's colour and four distractors one other colour, drawn from the seed. The
seed alone places the blocks and the target square; the variation chooses the colours and the height.
Success: exactly the asked number of target-coloured blocks stand on the square (RLBench counts at least
that many; exactly makes the number in the instruction matter) and the gripper holds nothing.
"""

import numpy as np
import sapien
import torch

from mani_skill.utils.building import actors
from mani_skill.utils.registration import register_env

from rvt2cli.record.motions import pick_and_place, solver
from rvt2cli.record.rlbench18.base import VariationEnv
from rvt2cli.record.rlbench18.colors import COLORS, other_color, rgba
from rvt2cli.record.rlbench18.layout import scatter

HEIGHTS = (2, 3, 4)             # blocks per tower: the variation is colour index * 3 + height index
BLOCKS = 4                      # of the target colour, and as many distractors
HALF = 0.02                     # m: half a block's side
SQUARE_HALF = 0.035             # m: half the target square's side; a block stands on it when its centre is over it
SQUARE_COLOR = [1.0, 0.85, 0.7, 1.0]  # pale peach: no colour an instruction names, and unlike the table
REGION = ((-0.22, -0.25), (0.12, 0.25))  # m: where blocks and the square lie (reachable, inside the scene bounds)
BLOCK_SPACING = 0.09            # m between block centres: the open gripper fits between neighbours
SQUARE_CLEARANCE = 0.13         # m from the square's centre to any block: the tower's approach stays clear


@register_env("RVT2-StackBlocks-v1", max_episode_steps=1000)
class StackBlocksEnv(VariationEnv):
    num_variations = len(COLORS) * len(HEIGHTS)

    @property
    def target_color(self) -> int:
        return self.variation // len(HEIGHTS)

    @property
    def height(self) -> int:
        return HEIGHTS[self.variation % len(HEIGHTS)]

    def _build_task(self, options):
        distractor = other_color(self._episode_rng, self.target_color)
        self.block_colors = [self.target_color] * BLOCKS + [distractor] * BLOCKS
        self.blocks = [actors.build_cube(self.scene, HALF, rgba(c), f"block_{i}",
                                         initial_pose=sapien.Pose(p=[0.5, i * 0.1, HALF]))
                       for i, c in enumerate(self.block_colors)]
        self.square = actors.build_box(self.scene, [SQUARE_HALF, SQUARE_HALF, 0.0005], SQUARE_COLOR, "target_square",
                                       body_type="kinematic", add_collision=False,
                                       initial_pose=sapien.Pose(p=[0.5, -0.2, 0.0005]))

    def _place_task(self, env_idx, options):
        rng = self._episode_rng
        square = scatter(rng, 1, *REGION, spacing=0)[0]
        self.square.set_pose(sapien.Pose(p=[*square, 0.0005]))
        blocks = scatter(rng, len(self.blocks), *REGION, spacing=BLOCK_SPACING, clear_of=[square],
                         clearance=SQUARE_CLEARANCE)
        yaws = rng.uniform(0, np.pi / 2, size=len(self.blocks))
        for block, xy, yaw in zip(self.blocks, blocks, yaws):
            block.set_pose(sapien.Pose(p=[*xy, HALF], q=[np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]))

    @property
    def targets(self) -> list:
        """The blocks wearing the instruction's colour (by the colours the scene was built with: after a
        change of variation, the blocks that the new instruction names, if any)."""
        return [b for b, c in zip(self.blocks, self.block_colors) if c == self.target_color]

    def _on_square(self, block) -> torch.Tensor:
        offset = block.pose.p - self.square.pose.p
        return (offset[:, :2].abs() <= SQUARE_HALF).all(dim=1) & (offset[:, 2] < 2 * HALF * (BLOCKS + 1))

    def evaluate(self):
        on_square = torch.stack([self._on_square(b) for b in self.blocks])  # [blocks, envs]
        named = torch.tensor([c == self.target_color for c in self.block_colors])[:, None]
        # no stillness test: PhysX leaves a resting tower's blocks a few cm/s of velocity it never damps
        stacked = (on_square & named).sum(dim=0)
        grasped = self.grasped(self.blocks).T  # [blocks, envs]
        wrong = ((on_square | grasped) & ~named).any(dim=0)
        return {"success": (stacked == self.height) & ~grasped.any(dim=0), "stacked": stacked, "wrong_object": wrong}


CARRY_CLEARANCE = 0.08  # m: a carried block's centre passes this far over the top of the tower it completes


def expert(env, seed=None):
    """Pick the target blocks one by one (the nearest to the square first) and stack them on the square.
    Returns -1 when a motion cannot be planned."""

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.9)
    square = scene.square.pose.sp.p
    blocks = sorted(scene.targets, key=lambda b: np.linalg.norm(b.pose.sp.p[:2] - square[:2]))[:scene.height]
    result = -1
    for level, block in enumerate(blocks):
        goal = [square[0], square[1], HALF + 2 * HALF * level]
        result = pick_and_place(planner, scene, block, goal, carry_z=2 * HALF * (level + 1) + CARRY_CLEARANCE)
        if result == -1:
            return -1
    return result
