"""Where keyframes come from during evaluation: the trained policy, or the ground truth (oracle)."""

import numpy as np
import torch

from rvt2cli.data import read_episode
from rvt2cli.data.keyframes import Keyframe
from rvt2cli.errors import UserError
from rvt2cli.eval.rollout import KeyframeSource
from rvt2cli.keyframes.extract import annotate, label_keyframes
from rvt2cli.keyframes.rule import KeyframeParams
from rvt2cli.model.language import InstructionCache
from rvt2cli.model.observation import Observation, observe, proprio_vector, stack_observations
from rvt2cli.model.rotation import yaw_rotate_quaternion
from rvt2cli.render.workspace import Workspace
from rvt2cli.record.expert import run_expert
from rvt2cli.record.scene import current_variation
from rvt2cli.robot import RobotFacts
from rvt2cli.tasks import Task
from rvt2cli.train.augment import yaw_matrices

# A re-prediction after an unreachable keyframe sees the scene shifted and turned by up to this much
# (well inside the training augmentation of 12.5 cm and 45 degrees), and its prediction is mapped back.
REPLAN_SHIFT_M = 0.03
REPLAN_YAW_DEG = 10.0


def expert_keyframes(env, task: Task, seed: int, params: KeyframeParams = KeyframeParams(), variation: int = 0):
    """The scripted expert's run on `seed` in this variation (its status, and its frames, which restore the
    scene) and the keyframes the rule finds in it, labelled as a recorded demo's are."""
    run = run_expert(env, task.expert, seed, max_frames=task.max_steps, variation=variation)
    frames = run.frames
    facts = RobotFacts.from_agent(env.unwrapped.agent)
    names = frames[0].state["joint_names"]
    arm_velocities = facts.arm(np.array([f.state["joint_velocities"] for f in frames]), names)
    return run, label_keyframes([f.gripper_command for f in frames], arm_velocities, [f.contacts for f in frames],
                                [f.state["tcp_pose"] for f in frames], params, [f.near for f in frames])


def predict_keyframes(policy, observations: list[Observation], workspaces: list[Workspace]) -> list[Keyframe]:
    """The policy's keyframe for each observation, in one forward pass, mapped to the world through each
    one's workspace."""
    pred = policy.predict(stack_observations(observations))
    return [Keyframe.from_pose([*workspace.to_world(pred.position[i].double().cpu()).numpy(),
                                *pred.quaternion[i].double().cpu().numpy()],
                               bool(pred.gripper_open[i]), bool(pred.ignore_collisions[i]))
            for i, workspace in enumerate(workspaces)]


class PredictingSource(KeyframeSource):
    """A source that predicts the next keyframe from the observation (`predict`), in the scene cube of
    `workspace`; asked again after an unreachable keyframe, it predicts from a seeded, perturbed
    observation and undoes the perturbation on the prediction."""

    workspace: Workspace
    seed: int = 0

    def predict(self, xyz, rgb, gripper_open, finger_positions, keyframes_done) -> Keyframe:
        raise NotImplementedError

    def next(self, cloud, gripper_open, finger_positions, keyframes_done, retry: int = 0) -> Keyframe:
        if retry == 0:
            return self.predict(cloud.xyz, cloud.rgb, gripper_open, finger_positions, keyframes_done)
        # a seeded perturbation of the observation, undone on the prediction
        g = np.random.default_rng([self.seed, keyframes_done, retry])
        yaw = np.radians(g.uniform(-REPLAN_YAW_DEG, REPLAN_YAW_DEG))
        shift = g.uniform(-REPLAN_SHIFT_M, REPLAN_SHIFT_M, size=3)
        center = np.asarray(self.workspace.center)
        turn = yaw_matrices(np.array([yaw]))[0]
        xyz = ((cloud.xyz - center) @ turn.T + center + shift).astype(np.float32)
        seen = self.predict(xyz, cloud.rgb, gripper_open, finger_positions, keyframes_done)
        position = (np.asarray(seen.position) - shift - center) @ turn + center
        quaternion = yaw_rotate_quaternion(np.asarray(seen.quaternion), np.array([-yaw]))[0]
        return Keyframe.from_pose([*position, *quaternion], seen.gripper_open, seen.ignore_collisions)


class PolicySource(PredictingSource):
    """The trained policy, in this process: cloud + instruction + proprio -> next keyframe."""

    def __init__(self, policy, checkpoint, device="cpu"):
        self.policy, self.device = policy, torch.device(device)
        self.cfg = policy.cfg
        self.checkpoint = checkpoint
        self.instructions = InstructionCache(self.cfg.lang_tokens, checkpoint.instruction_embeddings)

    def reset(self, task: Task, seed: int, instruction: str) -> None:
        """Observe the task's scene within the bounds it was trained with, for this instruction, aiming the
        task's aim offset once the gripper holds (a policy trained with one)."""
        self.workspace = Workspace.from_bounds(self.checkpoint.scene_bounds(task.name))
        self.lang = self.instructions([instruction])[0]
        self.aim_offset = self.checkpoint.aim_offset(task.name)
        self.seed = seed

    def observation(self, xyz, rgb, gripper_open, finger_positions, keyframes_done) -> Observation:
        return observe(xyz, rgb, proprio_vector(gripper_open, finger_positions, keyframes_done), self.lang,
                       self.workspace, self.device, self.aim_offset)

    def predict(self, xyz, rgb, gripper_open, finger_positions, keyframes_done) -> Keyframe:
        return predict_keyframes(self.policy, [self.observation(xyz, rgb, gripper_open, finger_positions, keyframes_done)],
                                 [self.workspace])[0]


class RemotePolicySource(PredictingSource):
    """A policy served by `rvt2 serve`, called over the network with `rvt2_client` as a robot calls it: the
    cloud, the instruction and the gripper's state go out, the keyframe comes back. The server answers what
    `PolicySource` answers in this process (the same checkpoint, the same scene bounds and aim)."""

    def __init__(self, url: str, token: str | None = None):
        from rvt2_client import PolicyClient

        self.client = PolicyClient(url, token=token)
        self.info = served_policy(self.client)

    def reset(self, task: Task, seed: int, instruction: str) -> None:
        self.task, self.instruction, self.seed = task.name, instruction, seed
        self.bounds = scene_bounds_of(self.info, task)
        self.workspace = Workspace.from_bounds(self.bounds)

    def predict(self, xyz, rgb, gripper_open, finger_positions, keyframes_done) -> Keyframe:
        from rvt2_client import PolicyError

        try:
            got = self.client.predict_cloud(xyz, rgb, self.instruction, bool(gripper_open), finger_positions,
                                            int(keyframes_done), task=self.task, scene_bounds=self.bounds)
        except PolicyError as e:
            raise UserError(f"{self.client.url} refused the episode's request: {e}") from None
        except (ConnectionError, TimeoutError) as e:
            raise UserError(f"{e}; the finished episodes are kept: run the same command with --resume once the "
                            "server is back") from None
        return Keyframe.from_pose([*got.position, *got.quaternion], got.gripper_open, got.ignore_collisions)


def served_policy(client) -> dict:
    """A served policy's description (GET /healthz's document), or one line saying why it cannot be had."""
    from rvt2_client import PolicyError

    try:
        return client.info()
    except (ConnectionError, TimeoutError) as e:
        raise UserError(f"{e}") from None
    except PolicyError as e:
        raise UserError(f"{client.url} refused: {e}" + ("; give --token-file" if e.field == "token" else "")) from None


def scene_bounds_of(info: dict, task: Task) -> list[float]:
    """The bounds a served policy observes `task` within: those it was trained with, else the task's own
    (as `Checkpoint.scene_bounds`)."""
    trained = info.get("tasks", {}).get(task.name)
    return list(trained["scene_bounds"]) if trained else list(task.scene_bounds)


class ReplaySource(KeyframeSource):
    """The keyframes a policy predicted in a recorded evaluation (its journal's records), in order,
    whatever the observation: what today's executor makes of the same predictions, without the model.
    Where the recorded run could not reach a keyframe it asked the policy again; where the replay
    reaches it, those re-predictions are skipped."""

    def __init__(self, records: list[dict]):
        self.records = {(r["task"], r["seed"]): r["steps"] for r in records if r["source"] == "policy"}

    def reset(self, task: Task, seed: int, instruction: str) -> None:
        self.steps, self.cursor = self.records[(task.name, seed)], 0

    def next(self, cloud, gripper_open, finger_positions, keyframes_done, retry: int = 0):
        if retry == 0:  # the last keyframe was reached: the recorded re-predictions of it are moot
            while self.cursor < len(self.steps) and self.steps[self.cursor]["retry"] > 0:
                self.cursor += 1
        if self.cursor >= len(self.steps):
            return None
        step = self.steps[self.cursor]
        self.cursor += 1
        return Keyframe.from_pose(step["target"], step["gripper_open"], step["ignore_collisions"])


class OracleSource(KeyframeSource):
    """Ground-truth keyframes, whatever the observation: those of a recorded demo of this seed if one
    was given, else those of the scripted expert run on the same seed, in the variation the scene is set
    to (without rendering). An
    unreachable keyframe has no alternative: the oracle moves on to its next one."""

    def __init__(self, env, demos: dict[tuple[str, int], str] | None = None, params: KeyframeParams = KeyframeParams()):
        self.env, self.demos, self.params = env, demos or {}, params

    def keyframes(self, task: Task, seed: int) -> list[Keyframe]:
        demo = self.demos.get((task.name, seed))
        if demo is not None:
            ep = read_episode(demo)
            return list((ep.keyframes or annotate(ep, self.params).keyframes).keyframes)
        return expert_keyframes(self.env, task, seed, self.params, current_variation(self.env))[1]

    def reset(self, task: Task, seed: int, instruction: str) -> None:
        self.queue = self.keyframes(task, seed)  # runs the expert, which resets the scene itself

    def next(self, cloud, gripper_open, finger_positions, keyframes_done, retry: int = 0):
        return self.queue[keyframes_done] if keyframes_done < len(self.queue) else None
