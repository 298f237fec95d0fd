"""rvt2cli.render: the point renderer (warp kernels + a torch reference), virtual camera rigs, and the
network's input channels. See docs/RENDERER.md."""

from .cameras import RVT1_VIEWS, RVT2_VIEWS, VIEW_AXES, Cameras, cube_rig, project, zoom_rig
from .channels import DEFAULT_SPLAT_RADIUS, NUM_CHANNELS, channels_from_render, network_images, render_scene
from .renderer import BACKENDS, Rendered, render

__all__ = [
    "BACKENDS",
    "DEFAULT_SPLAT_RADIUS",
    "NUM_CHANNELS",
    "RVT1_VIEWS",
    "RVT2_VIEWS",
    "VIEW_AXES",
    "Cameras",
    "Rendered",
    "channels_from_render",
    "cube_rig",
    "network_images",
    "project",
    "render",
    "render_scene",
    "zoom_rig",
]
