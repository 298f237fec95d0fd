"""The whole policy step as one module with fixed-shape tensor inputs, so it exports.

inputs:  xyz [1, N, 3] world metres (padded), rgb [1, N, 3] in [0, 1], num_points [1] (valid points),
         proprio [1, 4], lang [1, L, LANG_DIM] (instruction token embeddings), scene_bounds [6],
         aim_offset [3] (the task's, metres in the TCP frame, for a policy trained with `--aim-held`; else zeros)
outputs: position [1, 3] world metres, quaternion [1, 4] (x y z w), gripper_open [1] (1/0),
         ignore_collisions [1] (1/0), rotation_bins [1, 3]

Rendering (the pure-torch reference renderer), both stages and the 3D argmax are inside; so is the
observation contract's world -> cube mapping (`rvt2cli.model.observation`), computed from scene_bounds.
"""

import torch
from torch import nn

from rvt2cli.model.observation import LANG_DIM, Observation, aim_vector, proprio_vector
from rvt2cli.model.policy import RVT2Policy
from rvt2cli.render.workspace import center_and_half


class DeployablePolicy(nn.Module):
    def __init__(self, policy: RVT2Policy):
        super().__init__()
        self.policy = policy

    def forward(self, xyz, rgb, num_points, proprio, lang, scene_bounds, aim_offset):
        center, half = center_and_half(scene_bounds)
        obs = Observation(points=(xyz - center) / half, rgb=rgb, num_points=num_points, proprio=proprio, lang=lang,
                          aim=aim_vector(aim_offset, proprio[:, 0] > 0.5, half))
        pred = self.policy.predict(obs)
        position = pred.position * half + center
        # detached: a traced (TorchScript) module does not keep predict()'s no_grad, and the rotation now comes
        # from the scores, not from integer bins (and so does the TCP's offset from an aimed point)
        return position.detach(), pred.quaternion.detach(), pred.gripper_open.float(), pred.ignore_collisions.float(), pred.rot_bins


INPUT_NAMES = ["xyz", "rgb", "num_points", "proprio", "lang", "scene_bounds", "aim_offset"]
OUTPUT_NAMES = ["position", "quaternion", "gripper_open", "ignore_collisions", "rotation_bins"]


def example_inputs(cfg, max_points: int, generator: torch.Generator | None = None) -> tuple:
    """Inputs of the right shapes and kinds for tracing: a random cloud in the default scene, an open gripper."""
    from rvt2cli.tasks import DEFAULT_SCENE_BOUNDS

    g = generator or torch.Generator().manual_seed(0)
    proprio = proprio_vector(True, [0.04, 0.04], 0)
    return (torch.rand(1, max_points, 3, generator=g) * 0.6 - 0.3, torch.rand(1, max_points, 3, generator=g),
            torch.tensor([max_points]), torch.from_numpy(proprio)[None],
            torch.randn(1, cfg.lang_tokens, LANG_DIM, generator=g), torch.tensor(DEFAULT_SCENE_BOUNDS, dtype=torch.float32),
            torch.zeros(3))
