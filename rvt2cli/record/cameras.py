"""The real (simulated) camera rig: RLBench-like RGB-D cameras placed around the tabletop.

Fixed cameras are given by eye and target in the world frame (Panda base at x = -0.615, facing +x;
the table top is z = 0). The wrist camera rides on the Panda hand, where the `panda_wristcam` robot
has its camera, so every robot variant gets the same wrist view.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FixedCamera:
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov: float  # vertical field of view, rad


@dataclass(frozen=True)
class HandCamera:
    link: str
    position: tuple[float, float, float]         # in the link frame
    quaternion_wxyz: tuple[float, float, float, float]
    fov: float


CAMERAS = {
    "front": FixedCamera(eye=(0.75, 0.0, 0.6), target=(0.0, 0.0, 0.05), fov=1.0),
    "left_shoulder": FixedCamera(eye=(-0.45, 0.45, 0.65), target=(0.1, 0.0, 0.0), fov=1.0),
    "right_shoulder": FixedCamera(eye=(-0.45, -0.45, 0.65), target=(0.1, 0.0, 0.0), fov=1.0),
    # Pose of panda_wristcam's camera_link in the panda_hand frame (measured from ManiSkill 3.0.1).
    "wrist": HandCamera(link="panda_hand", position=(0.0465, -0.02, 0.036),
                        quaternion_wxyz=(0.0, 0.70711, 0.0, 0.70711), fov=float(np.pi / 2)),
}
SHADER = "default"  # float32 positions, so depth is not quantised to millimetres


def camera_configs(names, image_size: int, robot_links: dict):
    """ManiSkill CameraConfigs for the named cameras (imports ManiSkill lazily)."""
    import sapien
    from mani_skill.sensors.camera import CameraConfig
    from mani_skill.utils import sapien_utils

    configs = []
    for name in names:
        spec = CAMERAS[name]
        if isinstance(spec, FixedCamera):
            pose = sapien_utils.look_at(list(spec.eye), list(spec.target))
            configs.append(CameraConfig(name, pose, image_size, image_size, spec.fov, 0.01, 10.0, shader_pack=SHADER))
        else:
            pose = sapien.Pose(p=list(spec.position), q=list(spec.quaternion_wxyz))
            configs.append(CameraConfig(name, pose, image_size, image_size, spec.fov, 0.01, 10.0,
                                        mount=robot_links[spec.link], shader_pack=SHADER))
    return configs
