"""What RVT-2's second stage can see at each keyframe of recorded demos.

Stage 2 renders only the axis-aligned box of +-(workspace half extent / zoom) around its centre: +-10 cm
for the `rvt2` config in the default 0.8 m workspace. Its heatmap refines the position, and its features
alone feed the rotation, gripper and collision heads (unless the model is trained with
`--coarse-action-features`). A keyframe whose box holds nothing of the object that defines the pose
leaves stage 2 blind to it.

For every annotated demo of a task with a goal object (insert_peg: the box with the hole; plug_charger:
the receptacle) this resets the scene with the demo's seed, samples the object's oriented bounding box
(the surface, 6 x 21 x 21 points) and reports, per keyframe index, the share of those points inside the
stage-2 box centred on the keyframe's TCP, and in how many episodes none is; rows "before last" and "last"
gather the insertion and the pose before it whatever their index. With `--aim-held` the box is centred
where a policy trained with `rvt2 train --aim-held` centres it: on the task's aim offset (tasks/*.toml)
for keyframes that follow a closed gripper.

    rvt2 diagnose stage2-view DEMOS... [--config rvt2] [--zoom Z] [--aim-held] [--json out.json]
"""

from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from rvt2cli.data.paths import episode_paths
from rvt2cli.data.reader import read_episode
from rvt2cli.errors import UserError
from rvt2cli.model.config import get_config
from rvt2cli.model.observation import aim_vector, aimed_target
from rvt2cli.render.workspace import Workspace
from rvt2cli.tasks import TCP_AIM, get_task

GOAL_OBJECT = {"insert_peg": "box", "plug_charger": "receptacle"}   # the scene attribute holding each task's goal


def surface_points(actor, per_side: int = 21) -> np.ndarray:
    """[N, 3] world points on the surface of an actor's oriented bounding box."""
    from mani_skill.examples.motionplanning.base_motionplanner.utils import get_actor_obb

    obb = get_actor_obb(actor)
    grid = np.linspace(-0.5, 0.5, per_side)
    face = np.array([(a, b) for a in grid for b in grid])
    unit = np.concatenate([np.insert(face, axis, side, axis=1) for axis in range(3) for side in (-0.5, 0.5)])
    local = unit * np.asarray(obb.primitive.extents)
    transform = np.asarray(obb.primitive.transform)
    return local @ transform[:3, :3].T + transform[:3, 3]


def share_in_view(points: np.ndarray, centre: np.ndarray, half: float) -> float:
    return float(np.mean(np.all(np.abs(points - centre) <= half, axis=1)))


def measure(paths: list[Path], half: float, aim_held: bool = False) -> dict:
    from rvt2cli.record.scene import make_env

    shares: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    envs = {}
    for path in paths:
        ep = read_episode(path)
        task = ep.meta.task
        if task not in GOAL_OBJECT:
            continue
        if task not in envs:
            envs[task] = make_env(get_task(task), cameras=("front",), image_size=32)
        env = envs[task]
        env.reset(seed=ep.meta.seed)
        points = surface_points(getattr(env.unwrapped, GOAL_OBJECT[task]))
        keyframes = ep.require_keyframes().keyframes
        offset = torch.tensor(get_task(task).aim_offset if aim_held else TCP_AIM)
        for index, keyframe in enumerate(keyframes):
            observed_open = index == 0 or keyframes[index - 1].gripper_open   # the gripper where it is predicted
            aim = aim_vector(offset, torch.tensor([observed_open]), 1.0)[0].numpy()   # metres: the policy's rule
            centre = aimed_target(keyframe.position, keyframe.quaternion, aim)[0]
            share = share_in_view(points, centre, half)
            shares[task][str(index)].append(share)
            if index >= len(keyframes) - 2:   # the insertion and the pose before it, whatever their index
                shares[task]["last" if index == len(keyframes) - 1 else "before last"].append(share)
    for env in envs.values():
        env.close()
    return {task: {index: {"episodes": len(values), "mean_share": float(np.mean(values)),
                           "episodes_blind": int(sum(v == 0 for v in values))}
                   for index, values in by_index.items()}
            for task, by_index in shares.items()}


def report(demos, config: str = "rvt2", zoom: float | None = None, aim_held: bool = False) -> dict:
    """`measure` over annotated demos with the box of `config`'s zoom (or `zoom`) in the demos' workspace."""
    paths = episode_paths(list(demos))
    zoom = zoom or get_config(config).zoom
    half = Workspace.from_bounds(read_episode(paths[0]).meta.scene_bounds).half_extent / zoom
    tasks = measure(paths, half, aim_held)
    if not tasks:
        raise UserError(f"none of these demos is of a task with a goal object ({', '.join(GOAL_OBJECT)}); give demos of one")
    return {"zoom": zoom, "half_extent_m": half, "aim_held": aim_held, "tasks": tasks}


def markdown(report: dict) -> str:
    centre = "the aim offset once the gripper holds, else the TCP" if report["aim_held"] else "the TCP"
    lines = [f"stage 2 sees +-{report['half_extent_m'] * 1000:.0f} mm around its centre, {centre} (zoom {report['zoom']:g})", "",
             "| task | keyframe | episodes | share of the goal object's surface in view | episodes with none in view |",
             "|---|---|---|---|---|"]
    for task, rows in report["tasks"].items():
        for index, row in rows.items():
            lines.append(f"| {task} | {index} | {row['episodes']} | {row['mean_share']:.2f} | {row['episodes_blind']} |")
    return "\n".join(lines) + "\n"
