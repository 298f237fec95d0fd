"""Camera frames in, the next keyframe out: the policy as a robot program calls it.

    from rvt2cli.deploy import CameraFrame, KeyframePolicy

    policy = KeyframePolicy.load("runs/multi")          # a run folder, a checkpoint, or an `rvt2 export` folder
    keyframe = policy.predict(
        {"front": CameraFrame(rgb=rgb, depth=depth_mm, intrinsic=K, cam2world=pose)},   # one or more cameras
        instruction="put the block on the plate", gripper_open=True, finger_positions=(0.04, 0.04),
        keyframes_done=0, task="stack_blocks")
    keyframe.position, keyframe.quaternion, keyframe.gripper_open, keyframe.ignore_collisions

Each camera gives its colour image (uint8 [H, W, 3], RGB), its depth registered to the colour image
(float metres, or uint16 millimetres as RealSense gives it), its intrinsics K in OpenCV's (and ROS's)
convention, and its pose in the robot's base frame (x y z qx qy qz qw, OpenCV optical axes: x right, y
down, z forward), e.g. from a hand-eye calibration. The frames are fused, cropped to the task's scene
bounds and turned into the policy's observation exactly as in training (`rvt2cli.model.observation`);
the returned keyframe is in the base frame. A checkpoint runs in PyTorch; an exported folder runs its
ONNX or TorchScript file, with the same answers (the export is parity-checked).
"""

import json
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from rvt2cli.data.episode import CameraFrame, Cloud
from rvt2cli.data.fusion import depth_in_metres, fuse, intrinsic_from_opencv
from rvt2cli.data.keyframes import Keyframe
from rvt2cli.errors import UserError
from rvt2cli.model.language import InstructionCache
from rvt2cli.model.observation import aim_offset_or_tcp, colours, fit_points, proprio_vector

__all__ = ["CameraFrame", "Keyframe", "KeyframePolicy", "PolicyInput"]


@dataclass
class PolicyInput:
    """One observation as the model takes it: the fused cloud (base frame), the robot's state, the
    instruction's token embeddings, and the task's scene bounds and aim offset."""

    cloud: Cloud
    gripper_open: bool
    finger_positions: np.ndarray   # float32 [2], metres
    keyframes_done: int
    lang: torch.Tensor             # [L, LANG_DIM]
    bounds: list[float]
    aim_offset: list[float] | None


class KeyframePolicy:
    """A trained policy (a checkpoint or an exported folder) answering `predict(frames, ...)`.

    `predict` is `inputs` (fuse the frames, look up the instruction: per request, on the CPU) followed by
    `predict_inputs` (the model, for one input or a batch of them); `rvt2 serve` calls the two apart, so
    that requests from several robots share one forward pass."""

    kind = ""          # "checkpoint" | "export"
    device = "cpu"

    def __init__(self, tasks: dict[str, list[float]], lang_tokens: int, embeddings: dict[str, torch.Tensor],
                 aim_offsets: dict[str, list[float]] | None = None):
        self.tasks = tasks   # task -> scene bounds the policy was trained with
        self.aim_offsets = aim_offsets or {}  # task -> aim offset (policies trained with --aim-held)
        self.instructions = InstructionCache(lang_tokens, embeddings)
        self._embedding = threading.Lock()  # one thread embeds a new instruction at a time
    @staticmethod
    def load(path: str | Path, device: str = "cpu", stage2_min_points: int | None = None) -> "KeyframePolicy":
        """A checkpoint (`stage2_min_points` overrides its own) or an exported folder (fixed when exported)."""
        path = Path(path)
        if (path / "manifest.json").is_file():
            if stage2_min_points is not None:
                raise UserError(f"{path}: an exported policy keeps the stage-2 point minimum it was exported with; "
                                "export again with `rvt2 export --stage2-min-points N`")
            return _ExportedPolicy(path)
        return _CheckpointPolicy(path, device, stage2_min_points)

    def default_task(self, task: str | None) -> str | None:
        """`task`, or the policy's only task when none is given."""
        return next(iter(self.tasks)) if task is None and len(self.tasks) == 1 else task

    def scene_bounds(self, task: str | None, scene_bounds=None) -> list[float]:
        if scene_bounds is not None:
            return [float(v) for v in scene_bounds]
        task = self.default_task(task)
        if task not in self.tasks:
            raise UserError(f"give task= (one of {', '.join(self.tasks)}) or scene_bounds= for this policy")
        return list(self.tasks[task])

    @staticmethod
    def cloud(frames: dict[str, CameraFrame], bounds, opencv_intrinsics: bool = True) -> Cloud:
        """The fused cloud the policy sees: every camera's points in the base frame, cropped to the bounds."""
        prepared = {name: replace(f, depth=depth_in_metres(f.depth),
                                  intrinsic=intrinsic_from_opencv(f.intrinsic) if opencv_intrinsics else np.asarray(f.intrinsic))
                    for name, f in frames.items()}
        cloud = fuse(prepared, bounds)
        if len(cloud) == 0:
            raise UserError(f"no camera point lies inside the scene bounds {bounds}; check the camera poses "
                            "(camera-to-base, OpenCV axes) and the bounds")
        return cloud

    def inputs(self, frames: dict[str, CameraFrame], instruction: str, gripper_open: bool, finger_positions=(0.04, 0.04),
               keyframes_done: int = 0, task: str | None = None, scene_bounds=None,
               opencv_intrinsics: bool = True) -> PolicyInput:
        """What the model takes for these frames (see `predict`)."""
        bounds = self.scene_bounds(task, scene_bounds)
        return self.cloud_inputs(self.cloud(frames, bounds, opencv_intrinsics), instruction, gripper_open, finger_positions,
                                 keyframes_done, task, bounds)

    def cloud_inputs(self, cloud: Cloud, instruction: str, gripper_open: bool, finger_positions=(0.04, 0.04),
                     keyframes_done: int = 0, task: str | None = None, scene_bounds=None) -> PolicyInput:
        """What the model takes for a cloud fused by the caller (base frame, cropped to the scene bounds)."""
        bounds = self.scene_bounds(task, scene_bounds)
        with self._embedding:
            lang = self.instructions([instruction])[0]
        return PolicyInput(cloud, bool(gripper_open), np.asarray(finger_positions, np.float32), int(keyframes_done), lang,
                           bounds, self.aim_offsets.get(self.default_task(task)))

    def predict(self, frames: dict[str, CameraFrame], instruction: str, gripper_open: bool, finger_positions=(0.04, 0.04),
                keyframes_done: int = 0, task: str | None = None, scene_bounds=None,
                opencv_intrinsics: bool = True) -> Keyframe:
        """The next keyframe, in the frame the camera poses are given in (the robot's base)."""
        return self.predict_inputs([self.inputs(frames, instruction, gripper_open, finger_positions, keyframes_done, task,
                                                scene_bounds, opencv_intrinsics)])[0]

    def predict_inputs(self, inputs: list[PolicyInput]) -> list[Keyframe]:
        """Each input's keyframe (a checkpoint answers them in one forward pass)."""
        raise NotImplementedError

    def describe(self) -> dict:
        """What was loaded: its kind, path, weights file, model config and the camera rigs it was trained with."""
        raise NotImplementedError


class _CheckpointPolicy(KeyframePolicy):
    kind = "checkpoint"

    def __init__(self, path: Path, device: str, stage2_min_points: int | None = None):
        from rvt2cli.train.checkpoint import WEIGHTS, load_policy

        self.policy, self.checkpoint = load_policy(path, device=device, stage2_min_points=stage2_min_points)
        ckpt = self.checkpoint
        super().__init__({t: ckpt.scene_bounds(t) for t in ckpt.tasks}, self.policy.cfg.lang_tokens,
                         ckpt.instruction_embeddings, ckpt.aim_offsets)
        self.device, self.weights = device, ckpt.path / WEIGHTS

    def predict_inputs(self, inputs: list[PolicyInput]) -> list[Keyframe]:
        from rvt2cli.eval.sources import predict_keyframes
        from rvt2cli.model.observation import observe
        from rvt2cli.render.workspace import Workspace

        workspaces = [Workspace.from_bounds(i.bounds) for i in inputs]
        observations = [observe(i.cloud.xyz, i.cloud.rgb, proprio_vector(i.gripper_open, i.finger_positions, i.keyframes_done),
                                i.lang, workspace, self.device, i.aim_offset) for i, workspace in zip(inputs, workspaces)]
        return predict_keyframes(self.policy, observations, workspaces)

    def describe(self) -> dict:
        return {"kind": self.kind, "path": str(self.checkpoint.path), "weights": str(self.weights), "step": self.checkpoint.info.get("step"),
                "config": self.policy.cfg.to_dict(), "rigs": self.checkpoint.info.get("rigs", {}),
                "phrasings": self.checkpoint.training_options.get("phrasings")}


class _ExportedPolicy(KeyframePolicy):
    kind = "export"

    def __init__(self, folder: Path):
        from safetensors.torch import load_file

        from rvt2cli.export.exporter import is_export, load_exported

        if not is_export(folder):
            raise UserError(f"{folder}: not a policy written by `rvt2 export` (its manifest.json is not one)")
        manifest = json.loads((folder / "manifest.json").read_text())
        if "aim_offset" not in manifest.get("inputs", {}):
            raise UserError(f"{folder}: exported by an older rvt2 (its policy has no aim_offset input); "
                            "export the checkpoint again with `rvt2 export`")
        texts = json.loads((folder / manifest["instructions"]["texts"]).read_text())
        embeddings = load_file(str(folder / manifest["instructions"]["file"]))["embeddings"]
        super().__init__({t: v["scene_bounds"] for t, v in manifest["tasks"].items()}, manifest["config"]["lang_tokens"],
                         {t: embeddings[i] for i, t in enumerate(texts)},
                         {t: v["aim_offset"] for t, v in manifest["tasks"].items() if v.get("aim_offset")})
        self.run = load_exported(folder, manifest)
        self.manifest, self.folder = manifest, folder
        self.max_points = manifest["max_points"]

    def predict_inputs(self, inputs: list[PolicyInput]) -> list[Keyframe]:
        return [self._predict_one(i) for i in inputs]  # the exported graph takes a batch of one

    def _predict_one(self, i: PolicyInput) -> Keyframe:
        proprio = proprio_vector(i.gripper_open, i.finger_positions, i.keyframes_done)
        xyz, rgb, count = fit_points(i.cloud.xyz, i.cloud.rgb, self.max_points)
        position, quaternion, gripper_open, ignore_collisions, _ = self.run(
            torch.from_numpy(xyz)[None], colours(torch.from_numpy(rgb))[None], torch.tensor([count]),
            torch.from_numpy(proprio)[None], i.lang[None], torch.tensor(i.bounds, dtype=torch.float32),
            torch.tensor(aim_offset_or_tcp(i.aim_offset), dtype=torch.float32))
        return Keyframe.from_pose([*np.asarray(position)[0], *np.asarray(quaternion)[0]], bool(np.asarray(gripper_open)[0] > 0.5),
                                  bool(np.asarray(ignore_collisions)[0] > 0.5))

    def describe(self) -> dict:
        return {"kind": self.kind, "path": str(self.folder), "weights": str(self.folder / self.manifest["file"]),
                "step": self.manifest.get("step"), "config": self.manifest["config"], "format": self.manifest["format"],
                "max_points": self.max_points, "rigs": {}, "phrasings": None}

