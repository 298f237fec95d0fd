"""Experts that stop above the named target first (`expert_via_target`) for rvt2-18's two tasks whose colour
decides a place beside the target, experts that bring a tool down further behind what it pushes
(`expert_via_target_far_behind`, `expert_far_behind`), and `rvt2 record --expert` that records a task with another
expert, on the real simulator: the replacement solves the scene, the keyframe rule finds the stop above the named
target or the tool's landing further back, a tool landing short spoils the drag or sweep only with the tight
margin, and a recorded episode names the expert that made it; a bad `--expert` is one line."""

from dataclasses import replace

import numpy as np
import pytest

from conftest import assert_one_line_error
from rvt2cli.data import read_episode
from rvt2cli.eval.sources import expert_keyframes
from rvt2cli.record.recorder import RecordOptions, record
from rvt2cli.diagnose import precision_budget
from rvt2cli.record.rlbench18 import reach_and_drag, slide_block_to_color_target, sweep_to_dustpan_of_size
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


FAR_BEHIND = {"reach_and_drag": ("expert_via_target", "expert_via_target_far_behind",
                                  reach_and_drag.FAR_CLEARANCE_M - reach_and_drag.CLEARANCE_M),
              "sweep_to_dustpan_of_size": ("expert", "expert_far_behind",
                                           sweep_to_dustpan_of_size.FAR_BEHIND_M - sweep_to_dustpan_of_size.BEHIND_DIRT_M)}


@pytest.mark.parametrize("task_name", sorted(FAR_BEHIND))
def test_a_far_behind_expert_leaves_room_for_a_tool_landing_short(task_name):
    """The same scene: the tool lands the margin's difference further from where the push ends (which stays), and a
    landing 40 mm short of the expert's (precision-budget's ahead40) spoils the push with the tight margin only."""
    tight, far, extra_m = FAR_BEHIND[task_name]
    task = get_task(task_name)
    env = make_env(task, cameras=("front",), image_size=32)
    try:
        runs = {name: expert_keyframes(env, replace(task, expert=f"rvt2cli.record.rlbench18.{task_name}:{name}"), seed=20000)
                for name in (tight, far)}
    finally:
        env.close()
    (tight_run, tight_keys), (far_run, far_keys) = runs[tight], runs[far]
    assert tight_run.status == far_run.status == "success" and len(tight_keys) == len(far_keys)
    # the push ends where it did (a longer slide stops within a few mm of the same place)
    assert np.allclose(tight_keys[-1].position, far_keys[-1].position, atol=0.006)

    def run_up(keys):   # the landing (the keyframe before the push) to the push's end, across the table
        return np.linalg.norm(np.subtract(keys[-1].position[:2], keys[-2].position[:2]))
    assert abs(run_up(far_keys) - run_up(tight_keys) - extra_m) < 0.006
    experts = {name: {task_name: f"rvt2cli.record.rlbench18.{task_name}:{name}"} for name in (tight, far)}
    short = {name: precision_budget.budget([task_name], ["ahead40"], seeds=1, first_seed=20000, workers=1,
                                           experts=experts[name])["rows"][0]["successes"] for name in (tight, far)}
    assert short == {tight: 0, far: 1}


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
