"""Experts that stop above the named target first (`expert_via_target`) for rvt2-18's two tasks whose colour
decides a place beside the target, and `rvt2 record --expert` that records a task with another expert, on the
real simulator: the replacement solves the scene, the keyframe rule finds the stop above the named target,
and a recorded episode names the expert that made it; a bad `--expert` is one line."""

from dataclasses import replace

import numpy as np
import pytest

from conftest import assert_one_line_error
from rvt2cli.data import read_episode
from rvt2cli.eval.sources import expert_keyframes
from rvt2cli.record.recorder import RecordOptions, record
from rvt2cli.record.rlbench18 import reach_and_drag, slide_block_to_color_target
from rvt2cli.record.scene import make_env
from rvt2cli.tasks import get_task

pytestmark = pytest.mark.sim
VIA = {"reach_and_drag": (reach_and_drag.VIA_HEIGHT_M, reach_and_drag.SQUARE_HALF),
       "slide_block_to_color_target": (slide_block_to_color_target.VIA_HEIGHT_M, slide_block_to_color_target.TARGET_HALF)}


def named_target(task_name: str, scene):
    return scene.squares[scene.target_square] if task_name == "reach_and_drag" else scene.goal_target


@pytest.mark.parametrize("task_name", sorted(VIA))
def test_the_via_expert_solves_the_scene_with_a_keyframe_above_the_named_target(task_name):
    task = get_task(task_name)
    via = replace(task, expert=f"rvt2cli.record.rlbench18.{task_name}:expert_via_target")
    env = make_env(task, cameras=("front",), image_size=32)
    try:
        run, keyframes = expert_keyframes(env, via, seed=3, variation=2)
        target = named_target(task_name, env.unwrapped).pose.sp.p  # the scene as the expert left it: targets stay
    finally:
        env.close()
    assert run.status == "success"
    assert len(keyframes) == 7  # one stop more than the task's own expert's 6
    height, half = VIA[task_name]
    over = [i for i, k in enumerate(keyframes) if np.all(np.abs(np.subtract(k.position[:2], target[:2])) < half)]
    first = keyframes[over[0]]  # the first keyframe over the named target is the stop above it, before the push
    assert abs(first.position[2] - height) < 0.01 and over[0] < len(keyframes) - 3, [k.position for k in keyframes]


def test_record_with_another_expert_names_it_in_the_episode(tmp_path):
    spec = "rvt2cli.record.rlbench18.slide_block_to_color_target:expert_via_target"
    options = RecordOptions(cameras=("front",), image_size=32, obs_every=50,
                            experts=(("slide_block_to_color_target", spec),))
    summary = record("slide_block_to_color_target", 1, tmp_path, seed=1, options=options)
    assert summary.counts() == {"success": 1}
    episode = read_episode(tmp_path / "slide_block_to_color_target_0001.mcap")
    assert episode.meta.expert == spec and episode.meta.success


@pytest.mark.parametrize("expert, fragment", [
    ("reach_and_drag=rvt2cli.record.rlbench18.reach_and_drag:no_such_expert", "no such function"),
    ("turn_tap=rvt2cli.record.rlbench18.turn_tap:expert", "not among the tasks being recorded"),
])
def test_record_refuses_an_expert_it_cannot_use_before_writing_anything(cli, tmp_path, expert, fragment):
    result = cli("record", "--task", "reach_and_drag", "--episodes", "1", "--out", str(tmp_path / "demos"), "--expert", expert)
    assert_one_line_error(result, "--expert", fragment)
    assert not (tmp_path / "demos").exists()
