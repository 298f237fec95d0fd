"""put_item_in_drawer: open the named drawer (bottom, middle or top) and put the block inside it.

RLBench's success: the item lies inside the named drawer (a proximity sensor there). Here: the block's
centre is inside the drawer's walls, below their top. The seed places the cabinet and the block beside
it; the variation only names the drawer.
"""

import numpy as np
import sapien
import torch

from mani_skill.utils.building import actors
from mani_skill.utils.registration import register_env
from mani_skill.utils.structs import Pose

from rvt2cli.record.motions import solver, top_down_grasp
from rvt2cli.record.rlbench18 import cabinet
from rvt2cli.record.rlbench18.open_drawer import PULL_M, CabinetEnv, pull_open

ITEM_HALF = 0.02                # m: the block's half size
ITEM_COLOUR = (0.1, 0.45, 0.85, 1)
ITEM_BESIDE = (0.24, 0.28)      # m: the block lies this far across from the cabinet's middle...
ITEM_X = (-0.20, -0.08)         # ...at this world x
BACK_OFF_M = 0.10               # the open hand rises this far off the opened handle, turning to point down
LIFT_M = 0.08                   # the open hand waits this far above the block
LONGEST_STEPS = 300             # control steps: a 10 cm motion planned longer than this swings through a singular pose
DROP_ABOVE_M = 0.03             # the block is let go this far above the drawer's walls


@register_env("RVT2-PutItemInDrawer-v1", max_episode_steps=600)
class PutItemInDrawerEnv(CabinetEnv):
    num_variations = len(cabinet.DRAWERS)

    def _build_task(self, options: dict):
        super()._build_task(options)
        self.item = actors.build_cube(self.scene, half_size=ITEM_HALF, color=ITEM_COLOUR, name="item",
                                      initial_pose=sapien.Pose([0, 0.3, ITEM_HALF]))

    def _place_task(self, env_idx, options: dict):
        self._place_cabinet(env_idx)
        rng = self._episode_rng
        cabinet_y = self.cabinet.pose.p[0, 1].item()
        towards_middle = -1.0 if cabinet_y > 0 else 1.0
        p = [rng.uniform(*ITEM_X), cabinet_y + towards_middle * rng.uniform(*ITEM_BESIDE), ITEM_HALF]
        yaw = rng.uniform(-np.pi / 4, np.pi / 4)
        q = [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
        self.item.set_pose(Pose.create_from_pq(torch.tensor([p]), torch.tensor([q])))

    def item_in_drawer(self) -> torch.Tensor:
        """Whether the block's centre is inside each drawer: shape [num_envs, 3], in cabinet.DRAWERS's order."""
        inside = []
        for label in cabinet.DRAWERS:
            drawer = self.cabinet.links_map[f"{label}_drawer"]
            local = (drawer.pose.inv() * self.item.pose).p   # the drawer link's frame is the cabinet's, shifted
            index = cabinet.DRAWERS.index(label)
            floor = cabinet.slot_bottom(index) + cabinet.DRAWER_GAP + cabinet.WALL
            inside.append((local[:, 0] > cabinet.WALL) & (local[:, 0] < cabinet.DEPTH - 2 * cabinet.WALL)
                          & (local[:, 1].abs() < cabinet.WIDTH / 2 - 2 * cabinet.WALL)
                          & (local[:, 2] > floor) & (local[:, 2] < floor + cabinet.SLOT - 2 * cabinet.DRAWER_GAP))
        return torch.stack(inside, dim=1)

    def evaluate(self):
        inside = self.item_in_drawer()
        named = inside[:, self.variation]
        return {"success": named, "wrong_target": inside.any(dim=1) & ~named}


def expert(env, seed=None):
    """Open the named drawer (open_drawer's motions), let go of its handle, rise and turn the hand down, pick
    the block from above, lift it to just above the drawer's walls, carry it over the drawer's open part and let go."""
    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.75)
    drawer = scene.variation
    if pull_open(planner, scene, drawer) == -1:
        return -1
    planner.open_gripper()
    # rising and turning in one motion: rising alone passes near a singular pose in some scenes (a 10 cm rise
    # took 1372 control steps in one of 20). Where this one does too, back off the way the hand came first.
    grasp = top_down_grasp(scene, scene.item)
    risen = sapien.Pose(scene.agent.tcp.pose.sp.p + [0, 0, BACK_OFF_M], grasp.q)
    plan = planner.move_to_pose_with_screw(risen, dry_run=True)
    if plan == -1 or len(plan["position"]) > LONGEST_STEPS:
        backed = scene.agent.tcp.pose.sp * sapien.Pose([0, 0, -BACK_OFF_M])
        if planner.move_to_pose_with_screw(backed) == -1:
            return -1
        risen = sapien.Pose(backed.p, grasp.q)
    if planner.move_to_pose_with_screw(risen) == -1:
        return -1
    # level over to the block first, at the height the hand rose to: a slanting path would clip the open drawer
    if planner.move_to_pose_with_screw(sapien.Pose([*grasp.p[:2], risen.p[2]], grasp.q)) == -1:
        return -1
    if planner.move_to_pose_with_screw(sapien.Pose([0, 0, LIFT_M]) * grasp) == -1:
        return -1
    if planner.move_to_pose_with_screw(grasp, refine_steps=0) == -1:   # the arrival and the grasp: one keyframe
        return -1
    planner.close_gripper()

    # the block rises to the drop's height, then moves level over the middle of the drawer's part outside
    # the cabinet, the fingers closing across the cabinet
    walls_top = cabinet.slot_bottom(drawer) + cabinet.SLOT - cabinet.DRAWER_GAP
    drop_height = walls_top + DROP_ABOVE_M + ITEM_HALF
    if planner.move_to_pose_with_screw(sapien.Pose([*grasp.p[:2], drop_height], grasp.q)) == -1:
        return -1
    above = scene.in_cabinet_frame([-PULL_M / 2, 0.0, drop_height]).p
    across = scene.cabinet.pose.sp.to_transformation_matrix()[:3, 1]
    now = scene.agent.tcp.pose.to_transformation_matrix()[0, :3, 1].cpu().numpy()
    drop = scene.agent.build_grasp_pose(np.array([0, 0, -1.0]), across if across @ now >= 0 else -across, above)
    if planner.move_to_pose_with_screw(drop) == -1:
        return -1
    return planner.open_gripper()
