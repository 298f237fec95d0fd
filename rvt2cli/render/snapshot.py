"""`rvt2 render`: the virtual views the network sees at one frame of an episode, as PNG files.

Writes, per view, the colour and the depth image of the fixed rig (and of the zoomed rig when asked),
a contact sheet with every view side by side, and optionally the fused cloud as PLY. Rows from above
the renderer (a policy's heatmaps: `rvt2cli.eval.heatmaps`) are added through `overlay`.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rvt2cli.atomic import atomic_open, atomic_path, ensure_folder
from rvt2cli.data import read_episode
from rvt2cli.errors import UserError
from rvt2cli.render.cameras import RVT1_VIEWS, RVT2_VIEWS, cube_rig, zoom_rig
from rvt2cli.render.channels import DEFAULT_SPLAT_RADIUS, render_scene
from rvt2cli.render.workspace import Workspace


@dataclass
class ViewImages:
    name: str
    rgb: np.ndarray    # uint8 [H, W, 3]
    depth: np.ndarray  # uint8 [H, W], near = bright, background = black


def save_png(image: np.ndarray, path: Path) -> None:
    from PIL import Image

    with atomic_open(path) as f:
        Image.fromarray(image).save(f, format="PNG")


def view_images(rendered, views, prefix: str) -> list[ViewImages]:
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


def heat_overlay(rgb: np.ndarray, probs: np.ndarray) -> np.ndarray:
    """A heatmap (probabilities over the image) drawn in red over a view."""
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
        later = ep.keyframes.next_keyframe(frame)
        if later is None:
            raise UserError(f"{ep.path}: no keyframe after frame {frame}")
        world = torch.tensor(later.position, dtype=torch.float32)
    else:
        try:
            world = torch.tensor([float(v) for v in zoom_at.split(",")], dtype=torch.float32)
            assert world.shape == (3,)
        except (ValueError, AssertionError):
            raise UserError(f"--zoom-at {zoom_at!r}: give next-keyframe or X,Y,Z in metres (world frame)") from None
    return workspace.to_cube(world)[None]


def render_frame(path, frame: int, out_dir, zoom_at: str | None = None, ply: bool = False, overlay=None,
                 image_size: int = 224, rig: str = "rvt2", zoom: float = 4.0, splat_radius: float = DEFAULT_SPLAT_RADIUS,
                 backend: str = "warp") -> list[Path]:
    """`overlay(ep, frame, cloud, out, stem, written)`, if given, returns more contact-sheet rows (and
    writes its own images, adding their paths to `written`)."""
    ep = read_episode(path)
    ep.check_frame(frame)
    cloud = ep.cloud(frame)
    out = ensure_folder(out_dir)
    workspace = Workspace.from_bounds(ep.meta.scene_bounds)
    views = RVT2_VIEWS if rig == "rvt2" else RVT1_VIEWS
    points = workspace.to_cube(torch.from_numpy(cloud.xyz))[None]
    rgb = torch.from_numpy(cloud.rgb)[None].float() / 255.0
    stem = f"{ep.path.stem}_f{frame:04d}"
    written: list[Path] = []

    rendered = render_scene(points, rgb, cube_rig(views, image_size), image_size, splat_radius=splat_radius, backend=backend)
    images = view_images(rendered, views, "")
    rows = [[im.rgb for im in images], [im.depth for im in images]]
    if zoom_at:
        center = _zoom_center(ep, frame, zoom_at, workspace)
        zoomed = render_scene(points, rgb, zoom_rig(center, zoom, views, image_size), image_size,
                              splat_radius=splat_radius, backend=backend)
        zoom_images = view_images(zoomed, views, "zoom_")
        images += zoom_images
        rows += [[im.rgb for im in zoom_images], [im.depth for im in zoom_images]]
    if overlay:
        rows += overlay(ep, frame, cloud, out, stem, written)
    for im in images:
        for kind, data in (("rgb", im.rgb), ("depth", im.depth)):
            save_png(data, out / f"{stem}_{im.name}_{kind}.png")
            written.append(out / f"{stem}_{im.name}_{kind}.png")
    save_png(_contact_sheet(rows), out / f"{stem}_sheet.png")
    written.append(out / f"{stem}_sheet.png")
    if ply:
        import open3d as o3d

        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(cloud.xyz.astype(np.float64))
        pcd.colors = o3d.utility.Vector3dVector(cloud.rgb.astype(np.float64) / 255.0)
        target = out / f"{stem}_cloud.ply"
        with atomic_path(target) as tmp:
            if not o3d.io.write_point_cloud(str(tmp), pcd):
                raise UserError(f"{target}: could not write the PLY file")
        written.append(target)
    return written

