"""A policy's heatmaps over its own virtual views, for `rvt2 render --checkpoint`: where each stage
looks for the next keyframe, drawn over the views it rendered (the contact sheet's last rows)."""

from pathlib import Path

import numpy as np

from rvt2cli.eval.sources import PolicySource
from rvt2cli.render.channels import render_scene
from rvt2cli.render.snapshot import heat_overlay, save_png, view_images
from rvt2cli.tasks import get_task
from rvt2cli.train.checkpoint import load_policy


def heatmap_overlay(checkpoint: str, backend: str = "warp"):
    """An `overlay` for `rvt2cli.render.snapshot.render_frame`."""
    policy, ckpt = load_policy(checkpoint, render_backend=backend)
    source = PolicySource(policy, ckpt)

    def rows(ep, frame: int, cloud, out: Path, stem: str, written: list) -> list[list[np.ndarray]]:
        source.reset(get_task(ep.meta.task), ep.meta.seed, ep.instruction["text"])
        reached = 0 if ep.keyframes is None else ep.keyframes.keyframes_reached(frame)
        fingers = ep.meta.robot.fingers(ep.robot.joint_positions[frame], ep.robot.joint_names, str(ep.path))
        obs = source.observation(cloud.xyz, cloud.rgb, ep.robot.gripper_command[frame] > 0, fingers, reached)
        pred = policy.predict(obs)
        out_rows = []
        for s, stage in enumerate(pred.stages):
            probs = stage.logits.float().flatten(-2).softmax(-1).view_as(stage.logits)[0].numpy()
            rendered = render_scene(obs.points, obs.rgb, stage.cameras, policy.cfg.image_size, num_points=obs.num_points,
                                    splat_radius=policy.cfg.splat_radius, backend=backend)
            row = []
            for v, im in enumerate(view_images(rendered, policy.cfg.views, f"stage{s + 1}_")):
                overlay = heat_overlay(im.rgb, probs[v])
                save_png(overlay, out / f"{stem}_{im.name}_heatmap.png")
                written.append(out / f"{stem}_{im.name}_heatmap.png")
                row.append(overlay)
            out_rows.append(row)
        return out_rows

    return rows
