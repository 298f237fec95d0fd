"""put_money_in_safe: put the stack of bank notes on the named shelf (bottom, middle or top) of the safe.

RLBench's success: the money lies on the named shelf (a proximity sensor there) and the gripper holds
nothing. Our safe is an open box with two inner shelves (three shelf levels), its door already gone. The
seed places and turns the safe and places the money beside it; the variation only names the shelf.
"""

import numpy as np
import sapien
import torch

from mani_skill.utils.building import actors
from mani_skill.utils.registration import register_env
from mani_skill.utils.structs import Pose

from rvt2cli.record.motions import solver
from rvt2cli.record.rlbench18.base import VariationEnv, build_fixture
from rvt2cli.record.rlbench18.open_drawer import tilted_grasp

SHELVES = ("bottom", "middle", "top")          # RLBench's order (its variation index)
# The safe's frame: origin on the table under the middle of its open front, x into the safe, z up.
WIDTH, DEPTH = 0.26, 0.18                      # m: outer size across (y) and deep (x)
PLINTH, WALL, SLOT = 0.07, 0.01, 0.14          # m: what it stands on, its walls and shelves, one shelf's height
# (14 cm: room above the notes, carried CLEAR_M over the shelf, for the tilted hand to reach ENTER_M in)
HEIGHT = PLINTH + 4 * WALL + 3 * SLOT
SAFE_X = (0.03, 0.09)                          # m: the safe's front, world x
SAFE_Y = (-0.12, 0.12)
SAFE_YAW = np.pi / 8
MONEY_HALF = (0.05, 0.035, 0.015)              # m: the stack of notes (long, across, thick)
MONEY_BESIDE = (0.24, 0.28)                    # m: the money lies this far across from the safe's middle...
MONEY_X = (-0.12, -0.02)                       # ...at this world x
MONEY_YAW = np.pi / 8                          # ...turned at most this much from the safe's direction
# The expert grips the notes across their middle (gripped off it, they turn in the fingers under their own
# weight), this high above the table, the hand tilted down like open_drawer's.
GRIP_HEIGHT_M = 0.02
LIFT_M = 0.08
LINE_UP_M = 0.06               # the notes line up with the shelf this far before the safe: nearer, their way
                               # there from beside the safe can clip its front
# The tilted hand's centre enters a shelf only about 1.5 cm before the hand comes near the shelf above:
# the expert lets go of the notes there, with their middle just inside, and pushes them in by their end.
ENTER_M = 0.015
# The notes slide in this far above the shelf. The arm comes to rest about 3 mm below the poses the expert asks
# for with the notes in the hand, and replayed keyframes dip a millimetre more on the way: at 5 mm the notes
# cleared the shelf's front edge by about 1 mm and, replayed, their leading edge caught on it, the notes
# slid back in the fingers and fell out in front of the safe when let go.
CLEAR_M = 0.015
PUSH_M = 0.04                  # the closed fingers push the notes' end this far into the shelf

SAFE_COLOUR = (0.35, 0.37, 0.4, 1)
MONEY_COLOUR = (0.35, 0.6, 0.3, 1)


def shelf_floor(shelf: int) -> float:
    """The height of this shelf's top surface (m, safe frame)."""
    return PLINTH + WALL + shelf * (SLOT + WALL)


def _build_safe(scene):
    w, d = WIDTH / 2, DEPTH / 2
    boxes = [([d, 0, PLINTH / 2], [d, w, PLINTH / 2]),
             ([DEPTH - WALL / 2, 0, HEIGHT / 2], [WALL / 2, w, HEIGHT / 2])]
    boxes += [([d, side * (w - WALL / 2), HEIGHT / 2], [d, WALL / 2, HEIGHT / 2]) for side in (-1, 1)]
    boxes += [([d, 0, PLINTH + WALL / 2 + level * (SLOT + WALL)], [d, w - WALL, WALL / 2])
              for level in range(4)]  # the floor, two shelves, the top
    return build_fixture(scene, boxes, SAFE_COLOUR, "safe", at=(0.3, 0, 0))


@register_env("RVT2-PutMoneyInSafe-v1", max_episode_steps=500)
class PutMoneyInSafeEnv(VariationEnv):
    num_variations = len(SHELVES)

    def _build_task(self, options: dict):
        self.safe = _build_safe(self.scene)
        self.money = actors.build_box(self.scene, MONEY_HALF, MONEY_COLOUR, name="money",
                                      initial_pose=sapien.Pose([0, 0.3, MONEY_HALF[2]]))

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        x, y, yaw = rng.uniform(*SAFE_X), rng.uniform(*SAFE_Y), rng.uniform(-SAFE_YAW, SAFE_YAW)
        self.safe.set_pose(Pose.create(sapien.Pose([x, y, 0], [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])))
        towards_middle = -1.0 if y > 0 else 1.0
        p = [rng.uniform(*MONEY_X), y + towards_middle * rng.uniform(*MONEY_BESIDE), MONEY_HALF[2]]
        turn = yaw + rng.uniform(-MONEY_YAW, MONEY_YAW)
        self.money.set_pose(Pose.create(sapien.Pose(p, [np.cos(turn / 2), 0, 0, np.sin(turn / 2)])))

    def in_safe_frame(self, point) -> sapien.Pose:
        return self.safe.pose.sp * sapien.Pose(point)

    def money_on_shelf(self) -> torch.Tensor:
        """Whether the money's centre is on each shelf, inside the safe: shape [num_envs, 3], SHELVES's order."""
        local = (self.safe.pose.inv() * self.money.pose).p
        inside = (local[:, 0] > 0) & (local[:, 0] < DEPTH - WALL) & (local[:, 1].abs() < WIDTH / 2 - WALL)
        return torch.stack([inside & (local[:, 2] > shelf_floor(s)) & (local[:, 2] < shelf_floor(s) + SLOT)
                            for s in range(len(SHELVES))], dim=1)

    def evaluate(self):
        on_shelf = self.money_on_shelf()
        named = on_shelf[:, self.variation] & ~self.grasped([self.money])[:, 0]
        return {"success": named, "wrong_target": on_shelf.any(dim=1) & ~on_shelf[:, self.variation]}


def expert(env, seed=None):
    """Grip the notes across their middle, from behind and above; lift them; hold them level before the
    named shelf; slide them in; let go; push them further in by their end with the closed fingers; back off."""
    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.75)
    money = scene.money.pose.sp
    grip = money * sapien.Pose([0, 0, GRIP_HEIGHT_M - MONEY_HALF[2]])
    grasp = tilted_grasp(scene, sapien.Pose(q=money.q), grip.p)
    above = sapien.Pose(grasp.p + [0, 0, LIFT_M], grasp.q)
    if planner.move_to_pose_with_screw(above) == -1:
        return -1
    if planner.move_to_pose_with_screw(grasp, refine_steps=0) == -1:   # the arrival and the grasp: one keyframe
        return -1
    planner.close_gripper()
    if planner.move_to_pose_with_screw(above) == -1:
        return -1

    # where the TCP sits against the notes' underside and far end, as they now lie in the hand
    in_hand = scene.money.pose.sp.inv() * scene.agent.tcp.pose.sp
    below_tcp = in_hand.p[2] + MONEY_HALF[2]
    reach_ahead = MONEY_HALF[0] - in_hand.p[0]
    safe = scene.safe.pose.sp
    height = shelf_floor(scene.variation) + CLEAR_M + below_tcp
    before = tilted_grasp(scene, safe, scene.in_safe_frame([-reach_ahead - LINE_UP_M, 0, height]).p)
    inside = tilted_grasp(scene, safe, scene.in_safe_frame([ENTER_M, 0, height]).p)
    if planner.move_to_pose_with_screw(before) == -1:
        return -1
    if planner.move_to_pose_with_screw(inside) == -1:
        return -1
    planner.open_gripper()
    end = (safe.inv() * scene.money.pose.sp).p[0] - MONEY_HALF[0]    # the notes' end, as they now lie
    behind = tilted_grasp(scene, safe, scene.in_safe_frame([end - 0.02, 0, height]).p)
    if planner.move_to_pose_with_screw(behind) == -1:
        return -1
    planner.close_gripper()
    if planner.move_to_pose_with_screw(tilted_grasp(scene, safe, scene.in_safe_frame([end + PUSH_M, 0, height]).p)) == -1:
        return -1
    return planner.move_to_pose_with_screw(behind)
