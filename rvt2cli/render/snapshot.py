"""`rvt2 render`: the virtual views the network sees at one frame of an episode, as PNG files.

Writes, per view, the colour and the depth image of the fixed rig (and of the zoomed rig when asked),
a contact sheet with every view side by side, optionally the fused cloud as PLY, and, given a
checkpoint, the policy's predicted heatmaps over both stages' views.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rvt2cli.atomic import atomic_open
from rvt2cli.data import read_episode
from rvt2cli.errors import UserError
from rvt2cli.model.config import RVT1_VIEWS, RVT2_VIEWS
from rvt2cli.model.workspace import Workspace
from rvt2cli.render.cameras import cube_rig, zoom_rig
from rvt2cli.render.channels import DEFAULT_SPLAT_RADIUS, render_scene
from rvt2cli.tasks import get_task


@dataclass
class ViewImages:
    name: str
    rgb: np.ndarray    # uint8 [H, W, 3]
    depth: np.ndarray  # uint8 [H, W], near = bright, background = black


def _save_png(image: np.ndarray, path: Path) -> None:
    from PIL import Image

    with atomic_open(path) as f:
        Image.fromarray(image).save(f, format="PNG")


def _view_images(rendered, views, prefix: str) -> list[ViewImages]:
    rgb = (rendered.features[0, ..., 3:6].clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    hit = rendered.hit[0].numpy()
    out = []
    for v, name in enumerate(views):
        depth = rendered.depth[0, v].numpy()
        shade = np.zeros(depth.shape, np.uint8)
        if hit[v].any():
            d = depth[hit[v]]
            lo, hi = d.min(), d.max()
            shade[hit[v]] = (255 - 200 * (d - lo) / max(hi - lo, 1e-9)).astype(np.uint8)
        out.append(ViewImages(f"{prefix}{name}", rgb[v], shade))
    return out


def _overlay(rgb: np.ndarray, probs: np.ndarray) -> np.ndarray:
    heat = probs / max(probs.max(), 1e-12)
    out = rgb.astype(np.float32) * (1 - 0.6 * heat[..., None])
    out[..., 0] += 255 * 0.6 * heat
    return np.clip(out, 0, 255).astype(np.uint8)


def _contact_sheet(rows: list[list[np.ndarray]]) -> np.ndarray:
    gap = 4
    width = max(sum(im.shape[1] + gap for im in row) for row in rows)
    height = sum(max(im.shape[0] for im in row) + gap for row in rows)
    sheet = np.full((height, width, 3), 255, np.uint8)
    y = 0
    for row in rows:
        x = 0
        for im in row:
            im3 = im if im.ndim == 3 else np.repeat(im[..., None], 3, axis=2)
            sheet[y:y + im.shape[0], x:x + im.shape[1]] = im3
            x += im.shape[1] + gap
        y += max(im.shape[0] for im in row) + gap
    return sheet


def _zoom_center(ep, frame: int, zoom_at: str, workspace: Workspace) -> torch.Tensor:
    if zoom_at == "next-keyframe":
        if ep.keyframes is None:
            raise UserError(f"{ep.path}: --zoom-at next-keyframe needs keyframes; run `rvt2 extract-keyframes {ep.path}`")
        later = [k for k in ep.keyframes["keyframes"] if k["frame"] > frame]
        if not later:
            raise UserError(f"{ep.path}: no keyframe after frame {frame}")
        world = torch.tensor(later[0]["tcp_pose"][:3], dtype=torch.float32)
    else:
        try:
            world = torch.tensor([float(v) for v in zoom_at.split(",")], dtype=torch.float32)
            assert world.shape == (3,)
        except (ValueError, AssertionError):
            raise UserError(f"--zoom-at {zoom_at!r}: give next-keyframe or X,Y,Z in metres (world frame)") from None
    return workspace.to_cube(world)[None]


def render_frame(path, frame: int, out_dir, zoom_at: str | None = None, ply: bool = False, checkpoint: str | None = None,
                 image_size: int = 224, rig: str = "rvt2", zoom: float = 4.0, splat_radius: float = DEFAULT_SPLAT_RADIUS,
                 backend: str = "warp") -> list[Path]:
    ep = read_episode(path)
    ep.check_frame(frame)
    cloud = ep.cloud(frame)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    workspace = Workspace.from_bounds(ep.meta.scene_bounds)
    views = RVT2_VIEWS if rig == "rvt2" else RVT1_VIEWS
    points = workspace.to_cube(torch.from_numpy(cloud.xyz))[None]
    rgb = torch.from_numpy(cloud.rgb)[None].float() / 255.0
    stem = f"{ep.path.stem}_f{frame:04d}"
    written: list[Path] = []

    rendered = render_scene(points, rgb, cube_rig(views, image_size), image_size, splat_radius=splat_radius, backend=backend)
    images = _view_images(rendered, views, "")
    rows = [[im.rgb for im in images], [im.depth for im in images]]
    if zoom_at:
        center = _zoom_center(ep, frame, zoom_at, workspace)
        zoomed = render_scene(points, rgb, zoom_rig(center, zoom, views, image_size), image_size,
                              splat_radius=splat_radius, backend=backend)
        zoom_images = _view_images(zoomed, views, "zoom_")
        images += zoom_images
        rows += [[im.rgb for im in zoom_images], [im.depth for im in zoom_images]]
    if checkpoint:
        rows += _heatmap_rows(ep, frame, cloud, checkpoint, out, stem, written, backend)
    for im in images:
        for kind, data in (("rgb", im.rgb), ("depth", im.depth)):
            _save_png(data, out / f"{stem}_{im.name}_{kind}.png")
            written.append(out / f"{stem}_{im.name}_{kind}.png")
    _save_png(_contact_sheet(rows), out / f"{stem}_sheet.png")
    written.append(out / f"{stem}_sheet.png")
    if ply:
        import open3d as o3d

        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(cloud.xyz.astype(np.float64))
        pcd.colors = o3d.utility.Vector3dVector(cloud.rgb.astype(np.float64) / 255.0)
        target = out / f"{stem}_cloud.ply"
        tmp = target.with_name(f".{target.stem}.tmp{target.suffix}")
        if not o3d.io.write_point_cloud(str(tmp), pcd):
            raise UserError(f"{target}: could not write the PLY file")
        tmp.replace(target)
        written.append(target)
    return written


def _heatmap_rows(ep, frame, cloud, checkpoint, out: Path, stem: str, written: list, backend: str) -> list[list[np.ndarray]]:
    """The policy's heatmaps over its own views (both stages), next to its predicted point."""
    from rvt2cli.eval.sources import PolicySource
    from rvt2cli.train.checkpoint import load_policy

    policy, ckpt = load_policy(checkpoint, render_backend=backend)
    source = PolicySource(policy, ckpt)
    source.reset(get_task(ep.meta.task), ep.meta.seed, ep.instruction["text"])
    reached = 0 if ep.keyframes is None else sum(k["frame"] <= frame for k in ep.keyframes["keyframes"])
    obs = source.observation(cloud, ep.robot.gripper_command[frame] > 0, ep.robot.joint_positions[frame, -2:], reached)
    pred = policy.predict(obs)
    rows = []
    for s, stage in enumerate(pred.stages):
        probs = stage.logits.float().flatten(-2).softmax(-1).view_as(stage.logits)[0].numpy()
        rendered = render_scene(obs.points, obs.rgb, stage.cameras, policy.cfg.image_size, num_points=obs.num_points,
                                splat_radius=policy.cfg.splat_radius, backend=backend)
        views = _view_images(rendered, policy.cfg.views, f"stage{s + 1}_")
        row = []
        for v, im in enumerate(views):
            overlay = _overlay(im.rgb, probs[v])
            _save_png(overlay, out / f"{stem}_{im.name}_heatmap.png")
            written.append(out / f"{stem}_{im.name}_heatmap.png")
            row.append(overlay)
        rows.append(row)
    return rows
