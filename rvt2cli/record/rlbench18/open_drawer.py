"""open_drawer: pull the named drawer (bottom, middle or top) of a three-drawer cabinet open.

RLBench's success: the drawer's joint has moved more than 0.15 m. The seed places and turns the
cabinet; the variation only names the drawer.
"""

import numpy as np
import sapien
import torch

from mani_skill.utils.registration import register_env
from mani_skill.utils.structs import Pose

from rvt2cli.record.motions import solver
from rvt2cli.record.rlbench18 import cabinet
from rvt2cli.record.rlbench18.base import VariationEnv

OPENED_M = 0.15            # RLBench's JointCondition: the drawer counts as open past this
PULL_M = 0.18              # the expert pulls the handle this far (the drawer stops at cabinet.DRAWER_TRAVEL)
APPROACH_M = 0.06          # the open hand waits this far before the handle
# The hand grips the handle pointing into the cabinet, tilted down this much: from where the arm starts,
# mplib rarely finds a straight-line motion to a level hand; tilted 45 degrees it reaches every drawer but
# cannot pull the bottom one out, tilted 60 it does both in every scene tried.
GRIP_PITCH = np.radians(60)
CABINET_X = (0.07, 0.13)   # m: the cabinet's front, world x (clear of the hand where the arm starts)
CABINET_Y = (-0.12, 0.12)
CABINET_YAW = np.pi / 8    # rad: the cabinet turns at most this much either way (RLBench: pi/4)


class CabinetEnv(VariationEnv):
    """A cabinet of three drawers, placed and turned by the seed (shared with put_item_in_drawer)."""

    def _build_task(self, options: dict):
        self.cabinet = cabinet.build_cabinet(self.scene, "cabinet")

    def _place_cabinet(self, env_idx):
        rng = self._episode_rng
        x, y = rng.uniform(*CABINET_X), rng.uniform(*CABINET_Y)
        yaw = rng.uniform(-CABINET_YAW, CABINET_YAW)
        q = [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
        self.cabinet.set_pose(Pose.create_from_pq(torch.tensor([[x, y, 0.0]]), torch.tensor([q])))
        self.cabinet.set_qpos(torch.zeros((len(env_idx), len(cabinet.DRAWERS))))
        self.cabinet.set_qvel(torch.zeros((len(env_idx), len(cabinet.DRAWERS))))

    def drawer_opening(self) -> torch.Tensor:
        """How far each drawer is open (m): shape [num_envs, 3], in cabinet.DRAWERS's order."""
        return self.cabinet.get_qpos()

    def in_cabinet_frame(self, point) -> sapien.Pose:
        """A point given in the cabinet's frame, in the world, turned like the cabinet."""
        return self.cabinet.pose.sp * sapien.Pose(point)


@register_env("RVT2-OpenDrawer-v1", max_episode_steps=300)
class OpenDrawerEnv(CabinetEnv):
    num_variations = len(cabinet.DRAWERS)

    def _place_task(self, env_idx, options: dict):
        self._place_cabinet(env_idx)

    def evaluate(self):
        opened = self.drawer_opening() > OPENED_M
        named = opened[:, self.variation]
        others = opened.clone()
        others[:, self.variation] = False
        return {"success": named, "wrong_target": others.any(dim=1) & ~named}


def tilted_grasp(scene, frame: sapien.Pose, centre) -> sapien.Pose:
    """The TCP pose at `centre` pointing along `frame`'s x, tilted down GRIP_PITCH, the fingers closing along
    `frame`'s y (the way round nearest the way they face now)."""
    turn = frame.to_transformation_matrix()[:3, :3]
    approaching = turn @ [np.cos(GRIP_PITCH), 0.0, -np.sin(GRIP_PITCH)]
    closing = turn @ [0.0, 1.0, 0.0]
    now = scene.agent.tcp.pose.to_transformation_matrix()[0, :3, 1].cpu().numpy()
    return scene.agent.build_grasp_pose(approaching, closing if closing @ now >= 0 else -closing, centre)


def handle_grasp(scene, drawer: int, opened: float = 0.0) -> sapien.Pose:
    """The TCP pose gripping this drawer's handle with the drawer open `opened` m: pointing into the cabinet,
    tilted down, the fingers closing across the bar."""
    centre = scene.in_cabinet_frame(cabinet.handle_centre(drawer) - [opened, 0, 0]).p
    return tilted_grasp(scene, scene.cabinet.pose.sp, centre)


def pull_open(planner, scene, drawer: int):
    """Reach in front of the handle, grip it, pull the drawer PULL_M open. Returns -1 if planning fails,
    else the last step's result (the hand still gripping)."""
    grasp = handle_grasp(scene, drawer)
    if planner.move_to_pose_with_screw(grasp * sapien.Pose([0, 0, -APPROACH_M])) == -1:
        return -1
    if planner.move_to_pose_with_screw(grasp, refine_steps=0) == -1:  # the arrival and the grip: one keyframe
        return -1
    planner.close_gripper()
    return planner.move_to_pose_with_screw(handle_grasp(scene, drawer, opened=PULL_M))


def expert(env, seed=None):
    """Grip the named drawer's handle from the front and pull it straight out."""
    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.75)
    return pull_open(planner, scene, scene.variation)
