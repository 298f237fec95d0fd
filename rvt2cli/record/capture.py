"""What the cameras see: every rvt2 camera of a scene, rendered at the simulator's current state.

Where SAPIEN renders through CUDA (NVIDIA's driver), a scene's cameras are one SAPIEN camera group: one
render submission for all of them, the pictures handed over in CUDA memory, and the bodies' render
transforms computed on the GPU from one buffer of poses, which the CPU simulation's poses are written to
at every capture (ManiSkill's GPU simulation fills the same buffer from GPU PhysX). On one H200 host a
four-camera capture takes 3.8 ms this way against 14.8 ms camera by camera, and 15 processes capture 393
times a second against 116, because each capture holds NVIDIA's driver lock once instead of a dozen
times (`benchmarks/capture_bench.py`; docs/BENCHMARKS.md, "Camera captures"). The pictures are the
camera-by-camera ones but for an edge pixel here and there (at most 0.05% of a camera's pixels in that
benchmark): the GPU rounds the transforms its own way. With lavapipe (SAPIEN's CPU device) the cameras
render one by one, as ManiSkill renders them; `RVT2_CAPTURE=cameras` asks for that path everywhere.
"""

import logging
import os

import numpy as np
from scipy.spatial.transform import Rotation

from rvt2cli.data import CameraFrame

CHOICE_VARIABLE = "RVT2_CAPTURE"   # auto (default): a camera group where SAPIEN renders through CUDA | cameras
TEXTURES = ("Color", "Position", "Segmentation")
HIDDEN_FAR = 1.0e5   # m: where a hidden body's transform is put, so it is out of view whether or not the group
                     # honours its visibility (ManiSkill's GPU simulation hides bodies the same way)
log = logging.getLogger(__name__)


def capture_cameras(env, segmentation: dict | None = None) -> dict[str, CameraFrame]:
    """Render every rvt2 camera at the current simulator state (hidden objects stay hidden).
    If a dict is given as `segmentation`, each camera's per-pixel actor/link ids are put into it."""
    for obj in env.unwrapped._hidden_objects:
        obj.hide_visual()
    group = camera_group(env)
    if group is not None:
        return group.capture(segmentation)[0]
    return capture_camera_by_camera(env, segmentation)


def capture_camera_by_camera(env, segmentation: dict | None = None) -> dict[str, CameraFrame]:
    """ManiSkill's way: each camera renders and hands over its pictures on its own."""
    u = env.unwrapped
    u.scene.update_render(update_sensors=True, update_human_render_cameras=False)
    frames = {}
    for name in env.rvt2_cameras:
        sensor = u.scene.sensors[name]
        sensor.capture()
        tex = sensor.get_obs(rgb=True, depth=False, position=True, segmentation=True, apply_texture_transforms=False)
        ids = tex["Segmentation"][0, ..., 1].cpu().numpy()  # actor/link-level ids, 0 = nothing hit
        if segmentation is not None:
            segmentation[name] = ids
        frames[name] = camera_frame(tex["Color"][0, ..., :3].cpu().numpy(), tex["Position"][0, ..., :3].cpu().numpy(),
                                    ids, sensor.get_params())
    return frames


def camera_frame(color: np.ndarray, position: np.ndarray, ids: np.ndarray, params: dict) -> CameraFrame:
    """One camera's picture as rvt2 stores it, from SAPIEN's textures (colour in [0, 1], positions in the
    OpenGL camera frame, which looks along -z, and segmentation ids, 0 where nothing was hit) and the
    camera's ManiSkill parameters."""
    depth = np.where(ids > 0, -position[..., 2], 0.0).astype(np.float32)
    world2cam = params["extrinsic_cv"][0].cpu().numpy().astype(np.float64)
    rot_c2w = world2cam[:, :3].T
    cam2world = np.concatenate([-rot_c2w @ world2cam[:, 3], Rotation.from_matrix(rot_c2w).as_quat()])
    return CameraFrame(
        rgb=np.clip(np.rint(color * 255.0), 0, 255).astype(np.uint8),
        depth=depth,
        intrinsic=params["intrinsic_cv"][0].cpu().numpy().astype(np.float64),
        cam2world=cam2world,
    )


class CameraGroup:
    """The rvt2 cameras of one or more scenes as one SAPIEN camera group, its render transforms taken from a
    CUDA buffer of every render body's pose. Made for the scenes as they are: ManiSkill builds a new scene
    at each reset."""

    def __init__(self, envs):
        import sapien
        import torch

        self.envs = [env.unwrapped for env in envs]
        self.scenes = [u.scene.sub_scenes[0] for u in self.envs]
        systems = [scene.render_system for scene in self.scenes]
        self.bodies = [body for system in systems for body in system.render_bodies]
        for row, body in enumerate(self.bodies):
            for shape in body.render_shapes:
                shape.set_gpu_pose_batch_index(row)
        self.names = [list(env.rvt2_cameras) for env in envs]
        self.sensors = [[u.scene.sensors[name] for name in names] for u, names in zip(self.envs, self.names)]
        # a camera riding on a body (the wrist's, on the hand) takes its pose from that body's row too: the
        # group does not see the CPU side's camera poses once it renders
        entities = [body.entity for body in self.bodies]   # kept: SAPIEN hands out one Python object per entity while it lives
        for own in self.sensors:
            for sensor in own:
                camera = sensor.camera._render_cameras[0]
                row = next((row for row, entity in enumerate(entities) if entity is camera.entity), None)
                if row is not None:
                    camera.set_gpu_pose_batch_index(row)
        self.group = sapien.render.RenderSystemGroup(systems)
        self.cameras = self.group.create_camera_group([s.camera._render_cameras[0] for own in self.sensors for s in own],
                                                      list(TEXTURES))
        device = torch.device("cuda", self.cameras.get_picture_cuda(TEXTURES[0]).cuda_id)
        self.poses = torch.zeros((len(self.bodies), 7), dtype=torch.float32, device=device)
        self.group.set_cuda_poses(sapien.pysapien.CudaArray(self.poses))

    def update_transforms(self) -> None:
        """Every render body's transform at its simulator's current state (hidden ones far away)."""
        import torch

        for u in self.envs:   # the bodies' poses from the physics, and the cameras' (which move on the CPU side)
            u.scene.update_render(update_sensors=True, update_human_render_cameras=False)
        rows = np.empty((len(self.bodies), 7), dtype=np.float32)
        for row, body in enumerate(self.bodies):
            pose = body.entity_pose
            rows[row, :3], rows[row, 3:] = pose.p, pose.q
            if body.visibility == 0:
                rows[row, :3] += HIDDEN_FAR
        self.poses.copy_(torch.from_numpy(rows))
        self.group.update_render()

    def capture(self, segmentation: dict | None = None) -> list[dict[str, CameraFrame]]:
        """Each scene's CameraFrames, as `capture_camera_by_camera` gives them; `segmentation` gets the
        first scene's ids."""
        import torch

        self.update_transforms()
        self.cameras.take_picture()
        pictures = {name: self.cameras.get_picture_cuda(name).torch() for name in TEXTURES}
        colour = pictures["Color"][..., :3].cpu().numpy()
        position = pictures["Position"][..., :3].cpu().numpy()
        ids = pictures["Segmentation"][..., 1].to(torch.int32).cpu().numpy()
        frames, i = [], 0
        for names, sensors in zip(self.names, self.sensors):
            own = {}
            for name, sensor in zip(names, sensors):
                if segmentation is not None and not frames:
                    segmentation[name] = ids[i]
                own[name] = camera_frame(colour[i], position[i], ids[i], sensor.get_params())
                i += 1
            frames.append(own)
        return frames


_group_failed = False


def camera_group(env) -> CameraGroup | None:
    """The env's camera group for its current scene (made after each reset), or None where the cameras
    render one by one: lavapipe, `RVT2_CAPTURE=cameras`, or a SAPIEN that could not make one (said once)."""
    global _group_failed
    choice = os.environ.get(CHOICE_VARIABLE, "auto").strip().lower()
    u = env.unwrapped
    if _group_failed or choice == "cameras" or u.scene.backend.render_backend != "sapien_cuda":
        return None
    group = _current_group(u)
    if group is None:
        u._rvt2_camera_group = None   # the last scene's group goes before the new one is made
        try:
            group = CameraGroup([env])
        except RuntimeError as e:   # e.g. a Vulkan device CUDA cannot see
            _group_failed = True
            log.warning("rendering camera by camera: SAPIEN made no camera group (%s)", e)
            return None
        u._rvt2_camera_group = group
    return group


def _current_group(u) -> CameraGroup | None:
    """The group made for this env's current scene, if any (ManiSkill builds a new scene at each reset)."""
    group = getattr(u, "_rvt2_camera_group", None)
    return group if group is not None and group.scenes[0] is u.scene.sub_scenes[0] else None


def capture_path(env) -> str:
    """How this env's cameras are captured: "camera-group" or "camera-by-camera" (recorded in episodes)."""
    return "camera-group" if camera_group(env) is not None else "camera-by-camera"


def video_frame(env) -> np.ndarray:
    """The env's video camera at the current state (`env.render()`), with the render transforms a camera
    group uses brought up to date first: the group's scene takes them from the GPU, not from the CPU."""
    group = _current_group(env.unwrapped)
    if group is not None:
        group.update_transforms()
    return np.asarray(env.render()[0].cpu().numpy(), dtype=np.uint8)
