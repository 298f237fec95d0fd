"""The RVT-2 policy: observation -> next keyframe (position, rotation bins, gripper, collision flag).

Stage 1 renders the scene cube from fixed virtual views and predicts a heatmap per view; the 3D point
the heatmaps agree on is where stage 2 zooms in (training: the true target plus noise). Stage 2
re-renders the cloud around that point, predicts the final point, and the action head reads the
stage-2 features at that point (and stage 1's, with `coarse_action_features`). Inputs
(`rvt2cli.model.observation`) and outputs are in the normalised scene cube.

With an aim in the observation (`rvt2 train --aim-held`), the point the heatmaps find is where the
aim (a point 12 cm along insert_peg's held peg) goes, and the predicted TCP is that point less the aim
turned by the predicted rotation. Why: the TCP's target before the insertion lies in free space 15-21
cm before the box, where stage 2 sees none of it; the aim's lies within 6 cm of the hole.
"""

import math
from dataclasses import dataclass

import torch
from torch import nn

from rvt2cli.model.action_head import ActionHead
from rvt2cli.model.config import ModelConfig
from rvt2cli.model.heatmap import make_heatmap_head
from rvt2cli.model.locate import heatmaps_to_point
from rvt2cli.model.mvt import MultiViewTransformer
from rvt2cli.model.observation import Observation
from rvt2cli.model.rotation import decode_euler, decode_window, euler_to_quaternion, rotate_vectors
from rvt2cli.render.cameras import Cameras, cube_rig, project, zoom_rig
from rvt2cli.render.channels import network_images

MAX_SPLAT_PX = 8  # the renderer's default cap on a disc's radius


@dataclass
class StageOutput:
    cameras: Cameras
    tokens: torch.Tensor      # [B, V, D, t, t]
    logits: torch.Tensor      # [B, V, H, W] heatmap logits


@dataclass
class Prediction:
    position: torch.Tensor    # [B, 3] cube coordinates
    rot_bins: torch.Tensor    # [B, 3] the best bin per Euler axis
    quaternion: torch.Tensor  # [B, 4] x y z w: the bins refined by their neighbours' scores (rotation.decode_euler)
    gripper_open: torch.Tensor       # [B] bool
    ignore_collisions: torch.Tensor  # [B] bool
    stage1_position: torch.Tensor    # [B, 3]
    stages: list[StageOutput]


class Stage(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.mvt = MultiViewTransformer(cfg)
        self.heatmap = make_heatmap_head(cfg.width, cfg.patch_size, cfg.upsample_hidden, cfg.convex_upsampling)

    def forward(self, images: torch.Tensor, proprio: torch.Tensor, lang: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        tokens = self.mvt(images, proprio, lang)
        b, v = tokens.shape[:2]
        logits = self.heatmap(tokens.flatten(0, 1)).unflatten(0, (b, v))
        return tokens, logits


def points_in_box(obs: Observation, center: torch.Tensor, half: float) -> torch.Tensor:
    """How many of each observation's real points lie within `half` (cube units) of `center` [B, 3]: what
    a stage's views around that centre can show. [B] int."""
    inside = ((obs.points - center[:, None, :]).abs() <= half).all(dim=-1)
    real = torch.arange(obs.points.shape[1], device=obs.points.device)[None, :] < obs.num_points.reshape(-1, 1)
    return (inside & real).sum(dim=-1)


class RVT2Policy(nn.Module):
    def __init__(self, cfg: ModelConfig, render_backend: str = "warp"):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.render_backend = render_backend
        self.stages = nn.ModuleList(Stage(cfg) for _ in range(cfg.stages))
        self.action = ActionHead(cfg)

    # --- cameras and rendering --------------------------------------------------------------------
    def cameras(self, stage: int, batch: int, device, center: torch.Tensor | None = None) -> Cameras:
        if stage == 0:
            return cube_rig(self.cfg.views, self.cfg.image_size, batch_size=batch, device=device)
        return zoom_rig(center, zoom=self.cfg.zoom, views=self.cfg.views, image_size=self.cfg.image_size)

    def box(self, stage: int, center: torch.Tensor | None, like: torch.Tensor) -> tuple[torch.Tensor, float]:
        """The box a stage's views cover: (centre [B, 3], half extent)."""
        if stage == 0:
            return like.new_zeros(like.shape[0], 3), 1.0
        return center, 1.0 / self.cfg.zoom

    def splat_reach(self, stage: int) -> int:
        """The splatting window a stage needs, in pixels, known before any data (orthographic rigs)."""
        focal = self.cfg.image_size / 2 * (self.cfg.zoom if stage else 1.0)
        return min(MAX_SPLAT_PX, math.ceil(self.cfg.splat_radius * focal))

    @torch.no_grad()
    def render(self, obs: Observation, cameras: Cameras, stage: int) -> torch.Tensor:
        return network_images(obs.points, obs.rgb, cameras, self.cfg.image_size, num_points=obs.num_points,
                              splat_radius=self.cfg.splat_radius, backend=self.render_backend, reach_px=self.splat_reach(stage))

    def run_stage(self, stage: int, obs: Observation, center: torch.Tensor | None = None) -> StageOutput:
        cameras = self.cameras(stage, obs.points.shape[0], obs.points.device, center)
        images = self.render(obs, cameras, stage)
        tokens, logits = self.stages[stage](images, obs.proprio, obs.lang)
        return StageOutput(cameras, tokens, logits)

    def locate(self, stage: int, out: StageOutput, center: torch.Tensor | None) -> torch.Tensor:
        probs = out.logits.float().flatten(-2).softmax(-1).view_as(out.logits)
        box_center, half = self.box(stage, center, probs)
        return heatmaps_to_point(probs, self.cfg.views, box_center, half, window=self.cfg.search_window() if stage else 1.0)

    def action_features(self, outputs: list[StageOutput], location: torch.Tensor) -> torch.Tensor:
        """What the action head reads at `location`: the last stage's features, and stage 1's before
        them with `coarse_action_features`."""
        read = [(outputs[0], True)] if self.action.reads_coarse else []
        features = []
        for out, coarse in read + [(outputs[-1], False)]:
            uv, _ = project(location[:, None, :].float(), out.cameras)        # [B, V, 1, 2]
            probs = None if self.cfg.local_rotation_features else out.logits.float().flatten(-2).softmax(-1).view_as(out.logits)
            features.append(self.action.features(out.tokens, uv[:, :, 0], probs, coarse=coarse))
        return torch.cat(features, dim=-1)

    # --- training and inference -------------------------------------------------------------------
    def forward_train(self, obs: Observation, target_position: torch.Tensor, target_rot_bins: torch.Tensor,
                      stage2_center: torch.Tensor | None = None) -> dict:
        """Teacher-forced pass: stage 2 is centred on `stage2_center` (target + noise), the action head
        reads features at the target, the rotation heads see the true earlier bins."""
        outputs = [self.run_stage(0, obs)]
        if self.cfg.stages == 2:
            outputs.append(self.run_stage(1, obs, stage2_center))
        action = self.action(self.action_features(outputs, target_position), target_rot_bins)
        return {"stages": outputs, "action": action}

    forward = forward_train  # what DistributedDataParallel calls

    def compile_network(self, mode: str | None = None) -> None:
        """torch.compile the transformer stages and the action head in place (the renderer stays
        eager: warp kernels are opaque to the compiler). Weights and their names are unchanged. `mode`:
        torch.compile's (None: its default; e.g. "reduce-overhead", CUDA graphs of each compiled part).

        The graphs are specialised to the shapes of their first call (a training batch never changes
        size). Calls at other sizes (validation) and calls under a torch dispatch mode (the FLOP counter)
        belong inside `eager()`: the first would compile another graph for each size, and a first call
        under FlopCounterMode makes torch skip compiling these modules for good (until this was found,
        `rvt2 train --compile` trained eagerly: 512 samples/s at batch 192 on an H200, against 723 for
        the compiled step, benchmarks/loop_bench.py)."""
        for stage in self.stages:
            stage.compile(dynamic=False, mode=mode)
        self.action.compile(dynamic=False, mode=mode)

    @staticmethod
    def eager():
        """A context in which the compiled parts run eagerly (and nothing is compiled)."""
        return torch.compiler.set_stance("force_eager")

    @torch.no_grad()
    def predict(self, obs: Observation) -> Prediction:
        outputs = [self.run_stage(0, obs)]
        position = stage1 = self.locate(0, outputs[0], None)
        if self.cfg.stages == 2:
            outputs.append(self.run_stage(1, obs, stage1))
            position = self.locate(1, outputs[1], stage1)
            if self.cfg.stage2_min_points:
                blind = points_in_box(obs, stage1, 1.0 / self.cfg.zoom) < self.cfg.stage2_min_points
                position = torch.where(blind[:, None], stage1, position)
        action = self.action(self.action_features(outputs, position))
        scores = [action["rot_x"], action["rot_y"], action["rot_z"]]
        rot_bins = torch.stack([s.argmax(-1) for s in scores], dim=-1)
        euler = decode_euler(scores, window=decode_window(self.cfg.rotation_bins, self.cfg.rotation_sigma_deg))
        quaternion = euler_to_quaternion(euler)
        if obs.aim is not None:  # the heatmaps found the aim's target: the TCP's lies behind it
            behind = rotate_vectors(quaternion, obs.aim.float())
            position, stage1 = position - behind, stage1 - behind
        return Prediction(position=position, rot_bins=rot_bins, quaternion=quaternion,
                          gripper_open=action["gripper"].argmax(-1) == 1,
                          ignore_collisions=action["collision"].argmax(-1) == 1, stage1_position=stage1, stages=outputs)
