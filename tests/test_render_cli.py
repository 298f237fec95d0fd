"""`rvt2 render` on a recorded episode: views, zoomed views, heatmaps, PLY, and clear errors."""

import numpy as np
import pytest
from PIL import Image

from conftest import assert_one_line_error
from rvt2cli.eval.heatmaps import heatmap_overlay
from rvt2cli.render.snapshot import render_frame

pytestmark = pytest.mark.sim


def test_render_writes_views_zoom_heatmaps_and_ply(tiny_dataset, tiny_checkpoint, tmp_path):
    run_dir, _ = tiny_checkpoint
    episode = sorted(tiny_dataset.glob("*.mcap"))[0]
    written = render_frame(episode, 0, tmp_path, zoom_at="next-keyframe", ply=True, overlay=heatmap_overlay(str(run_dir)),
                           image_size=96)
    names = {p.name for p in written}
    stem = f"{episode.stem}_f0000"
    for view in ("top", "front", "right"):
        assert f"{stem}_{view}_rgb.png" in names and f"{stem}_zoom_{view}_depth.png" in names
        assert f"{stem}_stage1_{view}_heatmap.png" in names and f"{stem}_stage2_{view}_heatmap.png" in names
    top = np.asarray(Image.open(tmp_path / f"{stem}_top_rgb.png"))
    assert top.shape == (96, 96, 3)
    assert (top.sum(-1) > 0).mean() > 0.3  # the table covers much of the top view
    sheet = np.asarray(Image.open(tmp_path / f"{stem}_sheet.png"))
    assert sheet.shape[0] > 4 * 96 and sheet.shape[1] >= 3 * 96
    assert (tmp_path / f"{stem}_cloud.ply").stat().st_size > 10_000


def test_render_frame_errors(tiny_dataset, tmp_path, cli):
    episode = sorted(tiny_dataset.glob("*.mcap"))[0]
    assert_one_line_error(cli("render", episode, "--frame", "100000", "--out", tmp_path), "out of range", "frames 0..")
    assert_one_line_error(cli("render", episode, "--frame", "1", "--out", tmp_path), "frame 1 has no observation")
    assert_one_line_error(cli("render", episode, "--frame", "0", "--zoom-at", "a,b", "--out", tmp_path), "--zoom-at")
