"""What every rvt2-18 environment shares: the Panda on ManiSkill's table, and the variation of the episode.

A variation (which object, colour, target or order the instruction names) is chosen before the reset,
with `env.unwrapped.variation = k` or `env.reset(options={"variation": k})`, and stays until changed.
The seed alone lays out the scene: variations differ only in what the instruction asks and in the
success check (and, where the variation is a colour, in which object wears it), so a policy that
ignores the instruction cannot tell them apart.
"""

import numpy as np
import sapien

from mani_skill.agents.robots import Panda
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import sapien_utils
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
