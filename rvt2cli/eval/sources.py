"""Where keyframes come from during evaluation: the trained policy, or the ground truth (oracle)."""

import numpy as np
import torch

from rvt2cli.data import read_episode
from rvt2cli.eval.executor import KeyframeAction
from rvt2cli.eval.rollout import KeyframeSource
from rvt2cli.keyframes.extract import annotate, label_keyframes
from rvt2cli.keyframes.rule import KeyframeParams
from rvt2cli.model.language import InstructionCache
from rvt2cli.model.policy import Observation
from rvt2cli.model.rotation import bins_to_quaternion
from rvt2cli.model.workspace import Workspace
from rvt2cli.record.expert import run_expert
from rvt2cli.tasks import Task
from rvt2cli.train.samples import proprio_vector


class PolicySource(KeyframeSource):
    """The trained policy: cloud + instruction + proprio -> next keyframe."""

    def __init__(self, policy, checkpoint, device="cpu"):
        self.policy, self.device = policy, torch.device(device)
        self.cfg = policy.cfg
        self.bounds = checkpoint.info.get("bounds", {})
        self.instructions = InstructionCache(self.cfg.lang_tokens, checkpoint.instruction_embeddings)

    def reset(self, task: Task, seed: int, instruction: str) -> None:
        self.workspace = Workspace.from_bounds(self.bounds.get(task.name, task.scene_bounds))
        self.lang = self.instructions([instruction]).to(self.device)

    def observation(self, cloud, gripper_open, finger_positions, keyframes_done) -> Observation:
        """A world-frame cloud and the robot's state as the policy's input (batch of one, cube coordinates)."""
        xyz = torch.from_numpy(cloud.xyz).to(self.device)[None]
        return Observation(points=self.workspace.to_cube(xyz), rgb=torch.from_numpy(cloud.rgb).to(self.device)[None].float() / 255.0,
                           num_points=torch.tensor([len(cloud)], device=self.device),
                           proprio=torch.from_numpy(proprio_vector(gripper_open, finger_positions, keyframes_done)).to(self.device)[None],
                           lang=self.lang)

    def next(self, cloud, gripper_open, finger_positions, keyframes_done) -> KeyframeAction:
        pred = self.policy.predict(self.observation(cloud, gripper_open, finger_positions, keyframes_done))
        position = self.workspace.to_world(pred.position[0].double().cpu()).numpy()
        quaternion = bins_to_quaternion(pred.rot_bins[0].cpu().numpy(), self.cfg.rotation_bins)
        return KeyframeAction(position=position, quaternion=quaternion, gripper_open=bool(pred.gripper_open[0]),
                              ignore_collisions=bool(pred.ignore_collisions[0]))


def _actions_from_annotation(keyframes: list[dict]) -> list[KeyframeAction]:
    return [KeyframeAction(position=np.asarray(k["tcp_pose"][:3]), quaternion=np.asarray(k["tcp_pose"][3:]),
                           gripper_open=k["gripper_open"], ignore_collisions=k["ignore_collisions"]) for k in keyframes]


class OracleSource(KeyframeSource):
    """Ground-truth keyframes, whatever the observation: those of a recorded demo of this seed if one
    was given, else those of the scripted expert run on the same seed (without rendering)."""

    def __init__(self, env, demos: dict[tuple[str, int], str] | None = None, params: KeyframeParams = KeyframeParams()):
        self.env, self.demos, self.params = env, demos or {}, params

    def keyframes(self, task: Task, seed: int) -> list[KeyframeAction]:
        demo = self.demos.get((task.name, seed))
        if demo is not None:
            ep = read_episode(demo)
            return _actions_from_annotation(ep.keyframes["keyframes"] if ep.keyframes else annotate(ep, self.params).keyframes["keyframes"])
        frames = run_expert(self.env, task.expert, seed, max_frames=task.max_steps).frames
        _, entries = label_keyframes([f.gripper_command for f in frames], np.array([f.state["joint_velocities"] for f in frames]),
                                     [f.contacts for f in frames], [f.state["tcp_pose"] for f in frames], self.params)
        return _actions_from_annotation(entries)

    def reset(self, task: Task, seed: int, instruction: str) -> None:
        self.queue = self.keyframes(task, seed)  # runs the expert, which resets the scene itself

    def next(self, cloud, gripper_open, finger_positions, keyframes_done):
        return self.queue[keyframes_done] if keyframes_done < len(self.queue) else None
