"""What every rvt2-18 environment shares: the Panda on ManiSkill's table, and the variation of the episode.

A variation (which object, colour, target or order the instruction names) is chosen before the reset,
with `env.unwrapped.variation = k` or `env.reset(options={"variation": k})`, and stays until changed.
The seed alone lays out the scene: variations differ only in what the instruction asks and in the
success check (and, where the variation is a colour, in which object wears it), so a policy that
ignores the instruction cannot tell them apart.
"""

import numpy as np
import sapien
import torch

from mani_skill.agents.robots import Panda
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import common, sapien_utils
from mani_skill.utils.scene_builder.table import TableSceneBuilder

PANDA_BASE = (-0.615, 0.0, 0.0)  # m: where the Panda stands, as in ManiSkill's tabletop tasks


def build_fixture(scene, boxes, colour, name: str, at=(0.0, 0.0, 0.0)):
    """A kinematic fixture (a safe, a cupboard, a rack) made of boxes of one colour: `boxes` are
    (centre, half size) pairs in the fixture's frame, which starts at `at` until the episode places it."""
    builder = scene.create_actor_builder()
    material = sapien.render.RenderMaterial(base_color=list(colour))
    for centre, half in boxes:
        builder.add_box_collision(sapien.Pose(centre), half)
        builder.add_box_visual(sapien.Pose(centre), half, material=material)
    builder.initial_pose = sapien.Pose(list(at))
    return builder.build_kinematic(name=name)


class VariationEnv(BaseEnv):
    SUPPORTED_ROBOTS = ["panda"]
    agent: Panda
    num_variations = 1   # each task's module sets it; its TOML lists as many [[variations]]
    variation = 0

    def __init__(self, *args, robot_uids="panda", robot_init_qpos_noise=0.02, **kwargs):
        self.robot_init_qpos_noise = robot_init_qpos_noise
        # a variation may colour the objects when the scene is built: build it at every reset (make_env does
        # too), or a change of variation would keep the first episode's colours
        kwargs.setdefault("reconfiguration_freq", 1)
        super().__init__(*args, robot_uids=robot_uids, **kwargs)

    def reset(self, seed=None, options=None):
        if options and "variation" in options:
            self.variation = int(options["variation"])
        if not 0 <= self.variation < self.num_variations:
            raise ValueError(f"{type(self).__name__}: variation {self.variation} is outside 0..{self.num_variations - 1}")
        return super().reset(seed=seed, options=options)

    @property
    def _default_sensor_configs(self):  # rvt2 replaces these with its own rig (rvt2cli.record.cameras)
        return [CameraConfig("base_camera", pose=sapien_utils.look_at([0.3, 0, 0.6], [-0.1, 0, 0.1]),
                             width=128, height=128, fov=np.pi / 2, near=0.01, far=100)]

    @property
    def _default_human_render_camera_configs(self):
        return CameraConfig("render_camera", pose=sapien_utils.look_at([0.6, 0.7, 0.6], [0.0, 0.0, 0.35]),
                            width=512, height=512, fov=1, near=0.01, far=100)

    def grasped(self, actors) -> torch.Tensor:
        """`Panda.is_grasping` of each actor, [num_envs, len(actors)]: both fingers press on it with at least
        0.5 N, each within 85 degrees of the direction it closes in. On the CPU, `is_grasping` scans every
        contact of the scene twice per actor and call, and the success checks that ask it of every object
        at every step spent most of an expert's time in it; this is the same test from one scan."""
        if self.gpu_sim_enabled:
            return torch.stack([self.agent.is_grasping(actor) for actor in actors], dim=1)
        finger = {self.agent.finger1_link._bodies[0].entity: 0, self.agent.finger2_link._bodies[0].entity: 1}
        index = {actor._bodies[0].entity: i for i, actor in enumerate(actors)}
        impulses = np.zeros((2, len(actors), 3))   # on each finger from each actor, summed as ManiSkill sums them
        for contact in self.scene.px.get_contacts():
            first, second = (body.entity for body in contact.bodies)
            if first in finger and second in index:
                on, by, sign = finger[first], index[second], 1.0
            elif second in finger and first in index:   # the pair the other way round: ManiSkill negates its impulse
                on, by, sign = finger[second], index[first], -1.0
            else:
                continue
            impulses[on, by] += sign * np.sum([p.impulse for p in contact.points], axis=0)
        forces = common.to_tensor(impulses) / self.scene.px.timestep   # float32, as is_grasping has them
        strong = [torch.linalg.norm(forces[f], axis=1) >= 0.5 for f in range(2)]
        if not (strong[0] & strong[1]).any():
            return (strong[0] & strong[1])[None, :]   # no object pressed by both fingers: the angles cannot change that
        opening = [self.agent.finger1_link.pose.to_transformation_matrix()[..., :3, 1],
                   -self.agent.finger2_link.pose.to_transformation_matrix()[..., :3, 1]]
        pressed = [strong[f] & (torch.rad2deg(common.compute_angle_between(opening[f].expand(len(actors), 3), forces[f])) <= 85)
                   for f in range(2)]
        return (pressed[0] & pressed[1])[None, :]

    def _load_agent(self, options: dict):
        super()._load_agent(options, sapien.Pose(p=list(PANDA_BASE)))

    def _load_scene(self, options: dict):
        self.table_scene = TableSceneBuilder(env=self, robot_init_qpos_noise=self.robot_init_qpos_noise)
        self.table_scene.build()
        self._build_task(options)

    def _initialize_episode(self, env_idx, options: dict):
        self.table_scene.initialize(env_idx)
        self._place_task(env_idx, options)

    def _build_task(self, options: dict):
        """Build the task's objects (once per reset: rvt2 rebuilds the scene every episode)."""
        raise NotImplementedError

    def _place_task(self, env_idx, options: dict):
        """Lay out the objects from the episode's seed (`self._episode_rng`, or torch's seeded RNG)."""
        raise NotImplementedError
