"""The cameras' capture: a SAPIEN camera group with GPU transforms against camera by camera.

The camera group needs SAPIEN rendering through CUDA (NVIDIA's driver): these tests skip elsewhere
(`scripts/offline-gpu-host/gpu_bench.sh` runs them on a GPU machine). The camera-by-camera path, which
lavapipe renders, is what every other simulator test uses."""

import numpy as np
import pytest
import torch

from rvt2cli.data import read_episode
from rvt2cli.record.capture import capture_camera_by_camera, capture_cameras, capture_path
from rvt2cli.record.expert import run_expert
from rvt2cli.record.recorder import RecordOptions, record
from rvt2cli.record.scene import make_env, restore_sim_state, set_variation
from rvt2cli.runtime import use_vulkan_driver
from rvt2cli.tasks import episode_variation, get_task

GPU_RENDERING = pytest.mark.skipif(not torch.cuda.is_available() or use_vulkan_driver().name != "nvidia",
                                   reason="needs SAPIEN rendering through NVIDIA's driver and CUDA")
# The group's transforms are rounded on the GPU: an edge pixel here and there lands on the other side
# (at most 0.05% of a camera's pixels in benchmarks/capture_bench.py on an H200).
MOST_PIXELS_OFF = 0.002


def pixels_off(a, b) -> float:
    """The share of a camera's pixels whose colour differs by more than one level or depth by more than 1 mm."""
    colour = np.abs(a.rgb.astype(np.int32) - b.rgb.astype(np.int32)).max(-1) > 1
    depth = np.abs(a.depth - b.depth) > 0.001
    return float((colour | depth).mean())


@GPU_RENDERING
@pytest.mark.parametrize("task_name", ["open_drawer", "push_cube", "pick_cube", "stack_blocks"])
def test_the_camera_group_draws_what_the_cameras_draw(task_name):
    """Along an expert demo (the arm and what it moves in view of every camera, the wrist's too), and after a
    reset to another seed (a new scene: the group is made again): push_cube hides its goal from the
    cameras, pick_cube shows its goal sphere."""
    task = get_task(task_name)
    grouped, reference = make_env(task), make_env(task)
    for seed in (0, 1):
        run = run_expert(grouped, task.expert, seed, max_frames=task.max_steps, variation=episode_variation(seed, task.variation_choices()))
        set_variation(reference, episode_variation(seed, task.variation_choices()))
        reference.reset(seed=seed)
        for frame in run.frames[:: max(1, len(run.frames) // 5)]:
            restore_sim_state(grouped, frame.sim)
            restore_sim_state(reference, frame.sim)
            ids, reference_ids = {}, {}
            got, want = capture_cameras(grouped, ids), capture_camera_by_camera(reference, reference_ids)
            assert capture_path(grouped) == "camera-group"
            for name in task.cameras:
                assert pixels_off(got[name], want[name]) <= MOST_PIXELS_OFF, name
                assert (ids[name] == reference_ids[name]).mean() >= 1 - MOST_PIXELS_OFF, name
                np.testing.assert_allclose(got[name].cam2world, want[name].cam2world, atol=1e-6)
    grouped.close()
    reference.close()


@GPU_RENDERING
def test_recording_with_the_camera_group_writes_the_cameras_observations(tmp_path, monkeypatch):
    """`rvt2 record` writes the same episode either way: the same frames and states, the same observation
    frames, and pictures within the group's tolerance."""
    paths = {}
    for path_name in ("cameras", "auto"):
        monkeypatch.setenv("RVT2_CAPTURE", path_name)
        summary = record("turn_tap", 1, tmp_path / path_name, seed=0, options=RecordOptions())
        paths[path_name] = summary.successes[0].path
    by_camera, grouped = read_episode(paths["cameras"]), read_episode(paths["auto"])
    assert grouped.obs_frames == by_camera.obs_frames and grouped.num_frames == by_camera.num_frames
    assert grouped.meta.extra["capture"] == "camera-group" and by_camera.meta.extra["capture"] == "camera-by-camera"
    for frame in grouped.obs_frames:
        assert grouped.sim_state(frame) == by_camera.sim_state(frame)
        want = by_camera.cameras(frame)
        for name, got in grouped.cameras(frame).items():
            assert pixels_off(got, want[name]) <= MOST_PIXELS_OFF, (frame, name)
