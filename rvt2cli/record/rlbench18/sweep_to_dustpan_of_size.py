"""sweep_to_dustpan_of_size: sweep the dirt with the broom into the tall or the short dustpan.

RLBench's variations (`rlbench/tasks/sweep_to_dustpan_of_size.py`): the dustpan, tall or short. Success:
all five pieces of dirt inside the named dustpan (RLBench's proximity sensor in it).

Here the broom is a hand brush (a handle and a head, in the shape of a T) lying on the table, the dirt five
small cubes, and the dustpans two pans open towards the dirt, beyond it, one to either side (the seed picks which
side holds the tall one), their floors painted on the table so that the dirt slides in without a lip.
"""

import numpy as np
import sapien
import torch
from transforms3d.euler import euler2quat

from mani_skill.utils.registration import register_env

from rvt2cli.record.motions import heading, lower_and_slide, pick_up_tool, solver, tcp_for
from rvt2cli.record.rlbench18.base import VariationEnv

SIZES = ("tall", "short")
WALL_HEIGHTS = {"tall": 0.09, "short": 0.03}  # m: the dustpans' walls
PAN_WIDTH, PAN_DEPTH, WALL_HALF = 0.17, 0.10, 0.005  # m: inside the walls; wall half thickness
PAN_RGBA = [0.1, 0.35, 0.8, 1.0]  # both dustpans: only their size tells them apart
NUM_DIRT, DIRT_HALF = 5, 0.0075
DIRT_RGBA = [0.46, 0.31, 0.31, 1.0]  # RLBench's dirt
DIRT_SPREAD = 0.025                  # m: the dirt lies within this of its centre (both axes)
DIRT_X, DIRT_Y = (-0.02, 0.06), (-0.03, 0.03)
PAN_OPENING_M = 0.15                 # m from the dirt's centre to each dustpan's opening...
PAN_BEARING = np.radians(50.0)       # ...away from the robot (+x), turned this far to either side
HANDLE_HALF = (0.075, 0.01, 0.0125)   # the broom: a handle along its -x...
HEAD_HALF = (0.012, 0.06, 0.0125)    # ...ending in a head along its y; the broom's origin is the head's centre
BROOM_RGBA = [0.75, 0.6, 0.2, 1.0]
BROOM_X, BROOM_Y, BROOM_YAW = (-0.16, -0.13), (-0.05, 0.05), np.radians(15.0)


@register_env("RVT2-SweepToDustpanOfSize-v1", max_episode_steps=400)
class SweepToDustpanOfSizeEnv(VariationEnv):
    num_variations = len(SIZES)

    def _build_task(self, options: dict):
        self.dustpans = {size: self._build_dustpan(size) for size in SIZES}
        self.dirt = [self._build_box(f"dirt{i}", [DIRT_HALF] * 3, DIRT_RGBA) for i in range(NUM_DIRT)]
        builder = self.scene.create_actor_builder()
        handle = sapien.Pose([-HEAD_HALF[0] - HANDLE_HALF[0], 0, HANDLE_HALF[2] - HEAD_HALF[2]])
        for pose, half in ((sapien.Pose(), HEAD_HALF), (handle, HANDLE_HALF)):
            builder.add_box_collision(pose, half)
            builder.add_box_visual(pose, half, material=sapien.render.RenderMaterial(base_color=BROOM_RGBA))
        builder.initial_pose = sapien.Pose([0, 0, HEAD_HALF[2]])
        self.broom = builder.build(name="broom")

    def _build_box(self, name, half, rgba):
        builder = self.scene.create_actor_builder()
        builder.add_box_collision(half_size=half)
        builder.add_box_visual(half_size=half, material=sapien.render.RenderMaterial(base_color=rgba))
        builder.initial_pose = sapien.Pose([0, 0, half[2]])
        return builder.build(name=name)

    def _build_dustpan(self, size: str):
        """Three walls around a floor painted on the table, open towards the pan's -x: its origin is the
        middle of the opening, on the table."""
        height = WALL_HEIGHTS[size]
        builder = self.scene.create_actor_builder()
        material = sapien.render.RenderMaterial(base_color=PAN_RGBA)
        walls = [(sapien.Pose([PAN_DEPTH + WALL_HALF, 0, height / 2]), [WALL_HALF, PAN_WIDTH / 2 + 2 * WALL_HALF, height / 2])]
        for side in (-1, 1):
            walls.append((sapien.Pose([PAN_DEPTH / 2, side * (PAN_WIDTH / 2 + WALL_HALF), height / 2]),
                          [PAN_DEPTH / 2, WALL_HALF, height / 2]))
        for pose, half in walls:
            builder.add_box_collision(pose, half)
            builder.add_box_visual(pose, half, material=material)
        floor = [0.5 * c for c in PAN_RGBA[:3]] + [1.0]
        builder.add_box_visual(sapien.Pose([PAN_DEPTH / 2, 0, 0.001]), [PAN_DEPTH / 2, PAN_WIDTH / 2, 0.001],
                               material=sapien.render.RenderMaterial(base_color=floor))
        builder.initial_pose = sapien.Pose()
        return builder.build_kinematic(name=f"dustpan_{size}")

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        centre = np.array([rng.uniform(*DIRT_X), rng.uniform(*DIRT_Y)])
        for piece in self.dirt:
            xy = centre + rng.uniform(-DIRT_SPREAD, DIRT_SPREAD, 2)
            piece.set_pose(sapien.Pose([*xy, DIRT_HALF], euler2quat(0, 0, rng.uniform(-np.pi, np.pi))))
        tall_side = rng.choice([-1, 1])
        for size, side in zip(SIZES, (tall_side, -tall_side)):  # each opens towards the dirt
            bearing = side * PAN_BEARING
            opening = [*(centre + PAN_OPENING_M * np.array([np.cos(bearing), np.sin(bearing)])), 0]
            self.dustpans[size].set_pose(sapien.Pose(opening, euler2quat(0, 0, bearing)))
        broom = [rng.uniform(*BROOM_X), rng.uniform(*BROOM_Y), HEAD_HALF[2]]
        self.broom.set_pose(sapien.Pose(broom, euler2quat(0, 0, rng.uniform(-BROOM_YAW, BROOM_YAW))))

    def dirt_in(self, size: str) -> np.ndarray:
        """[5]: which pieces of dirt lie inside this dustpan (between its walls, past its opening)."""
        pan = self.dustpans[size].pose.sp
        inside = []
        for piece in self.dirt:
            x, y, z = (pan.inv() * piece.pose.sp).p
            inside.append(0.0 < x < PAN_DEPTH and abs(y) < PAN_WIDTH / 2 and z < WALL_HEIGHTS[size])
        return np.array(inside)

    def evaluate(self):
        named, other = SIZES[self.variation], SIZES[1 - self.variation]
        return {"success": torch.tensor([bool(self.dirt_in(named).all())]),
                "wrong_target": torch.tensor([bool(self.dirt_in(other).any())])}


GRIP_FROM_END_M = 0.025   # the fingers hold the handle this far from its end
BEHIND_DIRT_M = 0.015     # the head comes down this far behind the dirt nearest it
FAR_BEHIND_M = 0.045      # expert_far_behind's: room for a policy landing a few cm nearer the dirt
INTO_PAN_M = 0.065        # the head's face ends this far inside the opening
HOVER_M = 0.06
ABOVE_TABLE_M = 0.003     # the head's underside slides this far above the table


def expert(env, seed=None, behind=BEHIND_DIRT_M):
    """Grasp the broom's handle near its end, lift it, lower its head `behind` metres behind the dirt, facing
    the named dustpan, and sweep straight into it. Returns -1 when a motion cannot be planned."""

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.9)
    broom = scene.broom.pose.sp
    handle_end = broom * sapien.Pose([-HEAD_HALF[0] - 2 * HANDLE_HALF[0] + GRIP_FROM_END_M, 0, 0])
    if not pick_up_tool(planner, scene, scene.broom, handle_end.p):
        return -1

    pan = scene.dustpans[SIZES[scene.variation]].pose.sp
    inward = pan.to_transformation_matrix()[:3, 0]  # from the opening to the back wall
    dirt = np.array([piece.pose.sp.p for piece in scene.dirt])
    start = (dirt - pan.p) @ inward  # where each piece lies along the sweep, from the opening
    head = pan.p + (start.min() - DIRT_HALF - behind - HEAD_HALF[0]) * inward
    head[2] = HEAD_HALF[2] + ABOVE_TABLE_M
    down = tcp_for(scene, scene.broom, head, np.arctan2(inward[1], inward[0]) - heading(scene.broom.pose.sp))
    sweep = (INTO_PAN_M - HEAD_HALF[0]) - (head - pan.p) @ inward
    return lower_and_slide(planner, down, sweep * inward, HOVER_M)


def expert_far_behind(env, seed=None):
    """`expert` bringing the broom's head down FAR_BEHIND_M behind the dirt instead of BEHIND_DIRT_M. rvt2-18's failed
    sweeps mostly came down 4-6 cm nearer the dustpan than the expert, onto the dirt; the oracle's keyframes so moved
    sweep 23 of 50 scenes 40 mm nearer and none 60 mm nearer, with this margin 49 and 47 of 50 (`rvt2 diagnose
    precision-budget --variants ahead40,ahead60`; benchmarks/results/precision_budget/ahead_cpu/). Its scripted path
    stalls at the hover on a few seeds in 100 and runs past max_steps there (the default margin never does)."""
    return expert(env, seed, behind=FAR_BEHIND_M)
