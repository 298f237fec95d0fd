"""A task's ManiSkill scene with rvt2's camera rig, and what we read out of it each frame.

The environment steps with `obs_mode="none"` (no rendering while the expert runs); cameras are
rendered only on request with `rvt2cli.record.capture.capture_cameras`, typically after `env.set_state_dict(...)`.
"""

import gc
import logging
import re

import numpy as np

from rvt2cli.record.cameras import camera_configs
from rvt2cli.record.robot_visuals import lighten_robot_visuals
from rvt2cli.runtime import use_vulkan_driver
from rvt2cli.tasks import Task

FINGER_LINKS = ("panda_leftfinger", "panda_rightfinger")
CONTACT_IMPULSE = 1e-6  # N*s: contacts below this carry no force
MIN_HELD_WIDTH = 0.005  # m: fingers closer than this hold nothing (a closed gripper pushing with both tips)
NEAR_M = 0.005  # m: a body this close to the robot is "near" it (the motion planner's collision radius)


def _freeze_imported_objects() -> None:
    """Leave what exists now (the imported modules: torch, SAPIEN, ManiSkill) out of Python's garbage
    collections from now on. ManiSkill runs a full collection each time it rebuilds a scene, which rvt2
    does at every reset; scanning the modules' objects made that 0.13 s an episode."""
    global _frozen
    if not _frozen:
        gc.freeze()
        _frozen = True


_frozen = False


def make_env(task: Task, cameras=None, image_size: int | None = None, lighten: bool = True):
    """Build the task's environment (CPU physics, pd_joint_pos control) with our cameras, the Panda drawn from its
    lightened meshes (`rvt2cli.record.robot_visuals`; `lighten=False`: ManiSkill's). Its steps report no success:
    ask `env.unwrapped.evaluate()`."""
    driver = use_vulkan_driver()
    import mani_skill.envs  # noqa: F401 - registers the environments

    import rvt2cli.record.rlbench18  # noqa: F401 - registers rvt2-18's environments
    from mani_skill.utils.logging_utils import logger as mani_skill_logger

    _freeze_imported_objects()
    mani_skill_logger.setLevel(logging.ERROR)  # e.g. "no CUDA, rendering on the CPU": expected here
    # mplib's path timing (TOPP-RA) warns ("Fail to parametrize path", "A numerical error occurs") about every
    # path it cannot time, once per handler it has added (one per plan): the experts and the executor treat
    # such a path as none
    logging.getLogger("toppra.algorithm").setLevel(logging.ERROR)
    from mani_skill.utils.registration import REGISTERED_ENVS

    base = REGISTERED_ENVS[task.env_id].cls
    camera_names = tuple(task.cameras if cameras is None else cameras)
    size = image_size or task.image_size
    show = set(task.show_hidden)

    class RVT2Scene(base):
        @property
        def _default_sensor_configs(self):
            return camera_configs(camera_names, size, self.agent.robot.links_map)

        def _load_agent(self, *args, **kwargs):
            super()._load_agent(*args, **kwargs)
            if lighten:
                lighten_robot_visuals(self.agent.robot)

        def _load_scene(self, options):
            super()._load_scene(options)
            self._hidden_objects = [o for o in self._hidden_objects if o.name not in show]

        def get_info(self):
            # rvt2 asks the task's success check (`evaluate`) itself where it needs the answer (an expert's
            # end, an evaluation's keyframes), and reads nothing else of a step's info. ManiSkill's step asks
            # it after every control step, and the checks that look at every object cost rvt2-18's experts
            # about a quarter of their time.
            return {"elapsed_steps": self.elapsed_steps}

        @property
        def _default_human_render_camera_configs(self):
            configs = super()._default_human_render_camera_configs
            for config in configs if isinstance(configs, (list, tuple)) else [configs]:
                config.width = config.height = 256  # videos: software rendering is slow at 512 px
            return configs

    RVT2Scene.__name__ = f"RVT2{base.__name__}"
    # The scene is built anew at every reset (200 ms on the CPU): a reused PhysX scene carries contact and
    # solver state from one episode into the next, so an episode would depend on the episodes its process
    # ran before (which worker, in which order), not on its seed alone.
    kwargs = {"reconfiguration_freq": 1, **task.env_kwargs}
    # lavapipe is a CPU device: ManiSkill's default asks SAPIEN for a CUDA one, which lavapipe lacks on a
    # machine that has CUDA (there, "Failed to find a supported physical device")
    render = "cpu" if driver.name == "lavapipe" else "gpu"
    env = RVT2Scene(obs_mode="none", control_mode="pd_joint_pos", reward_mode="none", sim_backend="cpu",
                    render_backend=render, render_mode="rgb_array", **kwargs)
    env.rvt2_cameras = camera_names
    return env


def set_variation(env, variation: int) -> None:
    """Make the next reset lay out this variation (rvt2-18's environments); ManiSkill's own have only 0."""
    scene = env.unwrapped
    if hasattr(scene, "num_variations"):
        scene.variation = variation
    elif variation != 0:
        raise ValueError(f"{type(scene).__name__} has one variation, not {variation + 1}")


def current_variation(env) -> int:
    """The variation the scene lays out at its next reset (0 for ManiSkill's own environments)."""
    return int(getattr(env.unwrapped, "variation", 0))


def _wxyz_to_xyzw(q) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return np.array([q[1], q[2], q[3], q[0]])


def pose7(pose) -> np.ndarray:
    """A ManiSkill pose, of the first (only) scene -> [x y z qx qy qz qw]."""
    raw = pose.raw_pose[0].cpu().numpy()
    return np.concatenate([raw[:3], _wxyz_to_xyzw(raw[3:])])


def tcp_pose(env) -> np.ndarray:
    return pose7(env.unwrapped.agent.tcp.pose).astype(np.float32)


def robot_state(env) -> dict:
    robot = env.unwrapped.agent.robot
    qpos = robot.get_qpos()[0].cpu().numpy()
    qvel = robot.get_qvel()[0].cpu().numpy()
    return {
        "joint_names": [j.name for j in robot.get_active_joints()],
        "joint_positions": qpos,
        "joint_velocities": qvel,
        "gripper_width": float(qpos[-2] + qpos[-1]),
        "tcp_pose": tcp_pose(env),
    }


def _body_name(entity_name: str) -> str:
    """'scene-0_peg_0' -> 'peg' (ManiSkill prefixes the sub-scene and suffixes the instance)."""
    return re.sub(r"_\d+$", "", re.sub(r"^scene-\d+_", "", entity_name))


def _contact_table(contacts) -> list[tuple[str, str, list]]:
    """(entity name, entity name, contact points) of each PhysX contact, each read once: every read of a
    contact's bodies or points builds new Python objects, and a scene has a few hundred contacts a step."""
    return [(*(body.entity.name for body in contact.bodies), contact.points) for contact in contacts]


def _contact_pairs(table) -> list[tuple[str, str]]:
    """The (entity, entity) pairs of these contacts (`_contact_table`) that carry force. Each point's impulse
    norm is computed as np.linalg.norm computes it, sqrt(x . x), without its checks: a scene has tens of
    thousands of contact points per episode."""
    return [(a, b) for a, b, points in table
            if sum(float(np.sqrt(i.dot(i))) for i in (p.impulse for p in points)) > CONTACT_IMPULSE]


def _held(env, pairs) -> set[str]:
    """Entity names of objects between the fingers: touching both, with the gripper not shut."""
    qpos = env.unwrapped.agent.robot.get_qpos()[0]
    if float(qpos[-2] + qpos[-1]) <= MIN_HELD_WIDTH:
        return set()
    touching: dict[str, set[str]] = {}
    for a, b in pairs:
        touching.setdefault(a, set()).add(b)
        touching.setdefault(b, set()).add(a)
    return {body for body, others in touching.items() if all(f in others for f in FINGER_LINKS)}


def held_objects(env) -> set[str]:
    """Names (as robot_contacts gives them) of the objects in the gripper."""
    return {_body_name(n) for n in _held(env, _contact_pairs(_contact_table(env.unwrapped.scene.get_contacts())))}


def robot_contacts(env, margin: float = NEAR_M) -> tuple[list[str], list[str]]:
    """(touched, near): the scene bodies touched by the robot or by an object it holds (between both
    fingers), and those within `margin` of either, touching ones included. PhysX reports contact points,
    with their separation, for shapes closer than its contact offset (2 cm in ManiSkill scenes), so one
    contact query finds both, whether or not a body touches."""
    table = _contact_table(env.unwrapped.scene.get_contacts())
    pairs = _contact_pairs(table)
    grip = {link.name for link in env.unwrapped.agent.robot.get_links()} | _held(env, pairs)
    touched = {b for a, b in pairs if a in grip and b not in grip} | {a for a, b in pairs if b in grip and a not in grip}
    near = set()
    for a, b, points in table:
        if (a in grip) != (b in grip) and points and min(p.separation for p in points) <= margin:
            near.add(b if a in grip else a)
    return sorted({_body_name(n) for n in touched}), sorted({_body_name(n) for n in near})


def sim_state(env) -> dict:
    state = env.unwrapped.get_state_dict()
    return {group: {name: t[0].cpu().numpy().astype(np.float32).tolist() for name, t in items.items()}
            for group, items in state.items()}


def restore_sim_state(env, state: dict) -> None:
    import torch

    env.unwrapped.set_state_dict({group: {name: torch.tensor([values], dtype=torch.float32) for name, values in items.items()}
                                  for group, items in state.items()})


def segmentation_ids(env, body_names: set[str], include_robot: bool) -> np.ndarray:
    """Segmentation ids of the named scene bodies (as robot_contacts names them), and of every
    robot link if asked."""
    from mani_skill.utils.structs import Actor, Link

    ids = [seg_id for seg_id, obj in env.unwrapped.segmentation_id_map.items()
           if (include_robot and isinstance(obj, Link)) or (isinstance(obj, Actor) and _body_name(obj.name) in body_names)]
    return np.asarray(sorted(ids), dtype=np.int64)
