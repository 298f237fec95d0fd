"""What the policy sees: one contract for training, evaluation, rendering, export and deployment.

An observation is
- the fused point cloud of the scene (world frame, cropped to the task's scene bounds), mapped into the
  normalised scene cube [-1, 1]^3 of the task's workspace (`Workspace`), padded or randomly subsampled
  to a fixed number of points (`num_points` tells the renderer how many are real);
- the points' colours in [0, 1];
- the proprio vector (RLBench's low-dimensional state): gripper open (0/1), the two finger joints (m),
  and time, 1 at the start and -1 after `MAX_KEYFRAME_STEPS` keyframes (PerAct's);
- the instruction as `LANG_TOKENS`-or-so token embeddings of width `LANG_DIM` (all-MiniLM-L6-v2, zero
  rows after the last token; `rvt2cli.model.language`);
- for a policy trained with `rvt2 train --aim-held`, the aim: the point of the gripper's frame whose
  target the position heads predict (`aim_vector`). It is the task's `aim_offset` (along a held peg)
  while the gripper is closed, and the TCP itself (zeros) while it is open; the policy's prediction
  is always the TCP's.

Every producer of policy inputs builds them with the functions here.
"""

from dataclasses import dataclass

import numpy as np
import torch

from rvt2cli.render.workspace import Workspace
from rvt2cli.tasks import TCP_AIM

LANG_DIM = 384            # all-MiniLM-L6-v2 token embeddings
PROPRIO_DIM = 4           # gripper open, left finger, right finger, time
MAX_KEYFRAME_STEPS = 25   # the time feature counts keyframes reached over this horizon


@dataclass
class Observation:
    points: torch.Tensor      # [B, N, 3] cube coordinates (padded; see num_points)
    rgb: torch.Tensor         # [B, N, 3] in [0, 1]
    num_points: torch.Tensor  # [B] valid points per cloud
    proprio: torch.Tensor     # [B, PROPRIO_DIM]
    lang: torch.Tensor        # [B, L, LANG_DIM]
    aim: torch.Tensor | None = None  # [B, 3] cube units, in the TCP's frame (aim_vector); None: the TCP

    def to(self, device) -> "Observation":
        moved = [t.to(device, non_blocking=True) for t in (self.points, self.rgb, self.num_points, self.proprio, self.lang)]
        return Observation(*moved, aim=None if self.aim is None else self.aim.to(device, non_blocking=True))


def time_feature(keyframes_reached: int) -> float:
    """1 at the start of an episode, -1 after MAX_KEYFRAME_STEPS keyframes (PerAct's low-dim time)."""
    return 1.0 - 2.0 * min(keyframes_reached, MAX_KEYFRAME_STEPS) / MAX_KEYFRAME_STEPS


def proprio_vector(gripper_open: bool, finger_positions, keyframes_reached: int) -> np.ndarray:
    """[gripper open (0/1), left finger, right finger (m), time]."""
    return np.array([float(gripper_open), float(finger_positions[0]), float(finger_positions[1]),
                     time_feature(keyframes_reached)], dtype=np.float32)


def aim_vector(aim_offset_m: torch.Tensor, gripper_open: torch.Tensor, half_extent: torch.Tensor) -> torch.Tensor:
    """The aim of observations [B, 3] in cube units: the task's `aim_offset` (metres in the TCP frame,
    [3] or [B, 3]) where the gripper is closed (it holds what it aims with), zeros where it is open
    (`gripper_open` [B] bool). `half_extent` [B] or a number: metres per cube unit. Torch: exportable."""
    closed = (~gripper_open.reshape(-1, 1)).to(torch.float32)
    half = torch.as_tensor(half_extent, dtype=torch.float32).reshape(-1, 1)
    return aim_offset_m.to(torch.float32) * closed / half


def aim_offset_or_tcp(aim_offset) -> list[float]:
    """A task's aim offset as an exported policy's `aim_offset` input takes it: zeros where it has none."""
    return list(aim_offset) if aim_offset else list(TCP_AIM)


def aimed_target(tcp_position: np.ndarray, quaternion_xyzw: np.ndarray, aim_m: np.ndarray) -> np.ndarray:
    """Where the aim (m, TCP frame; [B, 3] or [3]) lies when the TCP is at these targets ([B, 3], [B, 4])."""
    from scipy.spatial.transform import Rotation

    return np.asarray(tcp_position, np.float64) + Rotation.from_quat(np.asarray(quaternion_xyzw).reshape(-1, 4)).apply(aim_m)


def fit_points(xyz: np.ndarray, rgb: np.ndarray, max_points: int,
               rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """A cloud as exactly `max_points` rows: a random subset (order kept) if it has more, zero rows
    after it if fewer. Returns (xyz [max_points, 3] float32, rgb [max_points, 3] like rgb, real rows)."""
    out_xyz = np.zeros((max_points, 3), np.float32)
    out_rgb = np.zeros((max_points, 3), rgb.dtype)
    return out_xyz, out_rgb, copy_points_into(out_xyz, out_rgb, xyz, rgb, points_kept(len(xyz), max_points, rng))


def points_kept(count: int, max_points: int, rng: np.random.Generator | None = None) -> np.ndarray | None:
    """Which of a cloud's `count` points `fit_points` keeps: a random `max_points` of them, in order, where
    it has more (drawn from `rng`); None, all of them, where it has no more."""
    if count <= max_points:
        return None
    rng = rng if rng is not None else np.random.default_rng(0)
    return np.sort(rng.choice(count, max_points, replace=False))


def copy_points_into(out_xyz: np.ndarray, out_rgb: np.ndarray, xyz: np.ndarray, rgb: np.ndarray,
                     keep: np.ndarray | None) -> int:
    """The points `keep` (`points_kept`; None: all) of a cloud into rows that are zero already (a packed
    array's [max_points, 3] rows): one copy of the cloud, none of the padding. Returns the real rows."""
    if keep is not None:
        xyz, rgb = xyz[keep], rgb[keep]
    out_xyz[: len(xyz)], out_rgb[: len(xyz)] = xyz, rgb
    return len(xyz)


def colours(rgb: torch.Tensor) -> torch.Tensor:
    """uint8 colours -> the policy's [0, 1] floats."""
    return rgb.float() / 255.0


def observe(xyz: np.ndarray, rgb: np.ndarray, proprio: np.ndarray, lang: torch.Tensor, workspace: Workspace,
            device="cpu", aim_offset=None) -> Observation:
    """One world-frame cloud (xyz [N, 3] m, rgb [N, 3] uint8) and the robot's state as a batch of one;
    `aim_offset` (m, TCP frame) for a policy trained with one for this task."""
    points = torch.from_numpy(np.ascontiguousarray(xyz, np.float32)).to(device)[None]
    proprio = np.asarray(proprio, np.float32)
    aim = None if aim_offset is None else aim_vector(torch.tensor(aim_offset), torch.tensor([proprio[0] > 0.5]), workspace.half_extent).to(device)
    return Observation(points=workspace.to_cube(points), rgb=colours(torch.from_numpy(np.ascontiguousarray(rgb)).to(device))[None],
                       num_points=torch.tensor([len(xyz)], device=device),
                       proprio=torch.from_numpy(proprio).to(device)[None],
                       lang=lang.to(device).reshape(1, *lang.shape[-2:]), aim=aim)


def stack_observations(observations: list[Observation]) -> Observation:
    """Observations of one each as one batch: every cloud padded with zero rows to the largest (its
    `num_points` keeps its own count), and zeros (the TCP) as the aim of those without one where others
    have one. The policy answers each as it answers it alone (exactly, on the CPU: tests/test_serve.py)."""
    if len(observations) == 1:
        return observations[0]
    rows = max(o.points.shape[1] for o in observations)

    def padded(t: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.pad(t, (0, 0, 0, rows - t.shape[1]))

    aims = None
    if any(o.aim is not None for o in observations):
        aims = torch.cat([o.proprio.new_zeros(1, 3) if o.aim is None else o.aim for o in observations])
    return Observation(points=torch.cat([padded(o.points) for o in observations]),
                       rgb=torch.cat([padded(o.rgb) for o in observations]),
                       num_points=torch.cat([o.num_points for o in observations]),
                       proprio=torch.cat([o.proprio for o in observations]),
                       lang=torch.cat([o.lang for o in observations]), aim=aims)
