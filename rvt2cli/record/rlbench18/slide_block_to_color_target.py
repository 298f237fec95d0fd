"""slide_block_to_color_target: slide the block onto the target of the colour the instruction names.

Four flat square targets, green, blue, pink and yellow, lie on the table around one block, each
TARGET_DISTANCE from it along one of four directions at right angles. The seed places the block, turns
the cross of directions and deals the colours to its arms; the variation (0-3: green, blue, pink, yellow,
RLBench's order) only says which target counts. RLBench's block ends in the target's proximity sensor;
here its centre must end over the target's square, on the table.
"""

import numpy as np
import sapien
import torch

from mani_skill.utils.building import actors
from mani_skill.utils.registration import register_env
from mani_skill.utils.structs.pose import Pose

from rvt2cli.record.rlbench18.base import VariationEnv

COLORS = {"green": (0.1, 0.7, 0.2), "blue": (0.1, 0.2, 0.9), "pink": (1.0, 0.4, 0.7), "yellow": (0.95, 0.85, 0.1)}
BLOCK_HALF = 0.025       # m
TARGET_HALF = 0.04       # m: half the side of a target square
TARGET_DISTANCE = 0.15   # m: block centre to each target's centre
BLOCK_RANGE = 0.05       # m: the block's centre lies within this of the table's centre, in x and y
BLOCK_COLOR = (0.6, 0.1, 0.1)


@register_env("RVT2-SlideBlockToColorTarget-v1", max_episode_steps=300)
class SlideBlockToColorTargetEnv(VariationEnv):
    """The block's centre lies over the named target's 8 cm square (within 4 cm of the square's centre
    along both its sides) and the block rests on the table. `wrong_target`: it lies over another
    target's square instead."""

    num_variations = len(COLORS)

    def _build_task(self, options: dict):
        self.block = actors.build_cube(self.scene, half_size=BLOCK_HALF, color=[*BLOCK_COLOR, 1], name="block",
                                       initial_pose=sapien.Pose(p=[0, 0, BLOCK_HALF]))
        # flat and without collision, like ManiSkill's goal regions: the block slides over them
        self.targets = [actors.build_box(self.scene, half_sizes=[TARGET_HALF, TARGET_HALF, 5e-4], color=[*rgb, 1],
                                         name=f"{name}_target", body_type="kinematic", add_collision=False,
                                         initial_pose=sapien.Pose(p=[0, 0, 5e-4]))
                        for name, rgb in COLORS.items()]

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        block = np.array([*rng.uniform(-BLOCK_RANGE, BLOCK_RANGE, size=2), BLOCK_HALF])
        turn = rng.uniform(-np.pi / 4, np.pi / 4)
        arms = rng.permutation(len(COLORS))  # target i lies along arm arms[i]
        self.block.set_pose(Pose.create_from_pq(p=torch.tensor(block[None], dtype=torch.float32)))
        for target, arm in zip(self.targets, arms):
            angle = turn + arm * np.pi / 2
            centre = block + TARGET_DISTANCE * np.array([np.cos(angle), np.sin(angle), 0.0])
            centre[2] = 5e-4
            q = [np.cos(angle / 2), 0, 0, np.sin(angle / 2)]  # wxyz: the square turned with its arm
            target.set_pose(Pose.create_from_pq(p=torch.tensor(centre[None], dtype=torch.float32),
                                                q=torch.tensor([q], dtype=torch.float32)))

    @property
    def goal_target(self):
        return self.targets[self.variation]

    def _over(self, target) -> torch.Tensor:
        """Whether the block's centre lies over this target's square."""
        offset = target.pose.inv() * self.block.pose
        return (offset.p[..., :2].abs() < TARGET_HALF).all(dim=-1)

    def evaluate(self):
        on_table = self.block.pose.p[..., 2] < BLOCK_HALF + 5e-3
        over = [self._over(t) & on_table for t in self.targets]
        wrong = torch.stack([o for i, o in enumerate(over) if i != self.variation]).any(dim=0)
        return {"success": over[self.variation], "wrong_target": wrong}


PUSH_HEIGHT = 0.02      # m: the TCP's height while it pushes (the closed fingertips just above the table)
BEHIND_M = 0.05         # m: the TCP starts this far behind the block's centre, clear of it
CONTACT_M = 0.035       # m: from the TCP to the block's centre while the closed fingers push it
LIFT_M = 0.08           # m: the TCP comes down onto its start from this high above it
VIA_HEIGHT_M = 0.10     # m: expert_via_target's stop above the named target


def expert(env, seed=None, via_target=False):
    """Close the gripper, come down behind the block on the far side from the named target, push it
    in a straight line until its centre is over the target's centre, and lift away; each motion ends at
    rest. The fingers face the push across their width. `via_target`: first stop above the named target.
    Returns -1 when a motion cannot be planned."""
    from rvt2cli.record.motions import solver

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.9)
    block = scene.block.pose.sp.p
    goal = scene.goal_target.pose.sp.p
    direction = np.array([*(goal - block)[:2], 0.0])
    direction /= np.linalg.norm(direction)
    # the fingers close across the push, the way nearest to how they close now (the wrist turns least)
    closing = np.array([-direction[1], direction[0], 0.0])
    if closing @ scene.agent.tcp.pose.to_transformation_matrix()[0, :3, 1].cpu().numpy() < 0:
        closing = -closing

    def pose(p):
        return scene.agent.build_grasp_pose(np.array([0, 0, -1.0]), closing, p)

    start = np.array([*(block - BEHIND_M * direction)[:2], PUSH_HEIGHT])
    end = np.array([*(goal - CONTACT_M * direction)[:2], PUSH_HEIGHT])
    planner.close_gripper()
    via = [np.array([*goal[:2], VIA_HEIGHT_M])] if via_target else []
    for p in (*via, start + [0, 0, LIFT_M], start, end, end + [0, 0, LIFT_M]):
        if planner.move_to_pose_with_screw(pose(p)) == -1:
            return -1
    return 0


def expert_via_target(env, seed=None):
    """`expert` with a stop above the named target first: the keyframe the instruction decides lies on the
    coloured target itself, as a named object's grasp does, rather than on the block's far side."""
    return expert(env, seed, via_target=True)
