"""rvt2 diagnose target-choice (rvt2cli/diagnose/target_choice.py): the target a push went for, on scenes the real
simulator rebuilds from the published rvt2-18 oracle's journal (the expert's keyframes, which always choose the named
target)."""

import numpy as np
import pytest

from rvt2cli.diagnose import target_choice
from benchmarks.experiment import REPOSITORY
from rvt2cli.eval.journal import read_journal
from rvt2cli.record.scene import make_env
from rvt2cli.tasks import get_task

pytestmark = pytest.mark.sim
ORACLE = REPOSITORY / "benchmarks" / "results" / "rvt2_18_h100x4" / "oracle" / "episodes.jsonl.xz"


def test_the_oracle_pushes_towards_the_named_target_every_time():
    _, records = read_journal(ORACLE)
    picked = [r for task in target_choice.TASKS for r in [r for r in records if r["task"] == task][:4]]
    envs = {task: make_env(get_task(task), cameras=[]) for task in target_choice.TASKS}
    try:
        rows = target_choice.episode_choices(envs, picked, source="oracle")
    finally:
        for env in envs.values():
            env.close()
    assert [r["seed"] for r in rows] == [r["seed"] for r in picked]
    assert all(r["chosen"] == r["named"] and r["success"] for r in rows)
    assert all(len(set(r["colours"])) == r["targets"] for r in rows)  # each target its own colour
    # the scenes differ: the named target is not always the same one
    assert len({(r["task"], r["named"]) for r in rows}) > 2
    summary = target_choice.summarise(rows)
    assert summary["reach_and_drag"]["named_chosen"] == 4 and summary["reach_and_drag"]["chance"] == pytest.approx(1 / 3)
    assert summary["slide_block_to_color_target"]["chance"] == pytest.approx(1 / 4)


def test_a_push_between_two_targets_is_no_clear_choice():
    layout = target_choice.Layout(np.zeros(2), [np.array([-0.2, 0.0]), np.array([0.0, 0.2])], ["red", "blue"], named=0)
    low = target_choice.SWEEP_HEIGHT_M / 2
    towards_first = target_choice.push([[0.1, 0.1, 0.1], [0.0, 0.0, low], [-0.15, 0.01, low]])
    assert target_choice.chosen_target(layout, towards_first) == 0
    assert target_choice.chosen_target(layout, np.array([-0.1, 0.1])) is None  # 45 degrees from each
    assert target_choice.push([[0.0, 0.0, low], [0.0, 0.2, 0.1]]) is None      # it rose: no sweep


def test_the_via_stop_is_the_keyframe_two_before_the_push():
    layout = target_choice.Layout(np.zeros(2), [np.array([-0.2, 0.0]), np.array([0.0, 0.2])], ["red", "blue"], named=0)
    low = target_choice.SWEEP_HEIGHT_M / 2
    stop_over_blue, hover, down, pushed = [0.02, 0.19, 0.12], [0.05, 0.0, 0.08], [0.05, 0.0, low], [-0.15, 0.0, low]
    keyframes = [[0.0, -0.3, 0.1], stop_over_blue, hover, down, pushed]
    assert target_choice.via_stop(layout, keyframes) == 1           # nearest blue, though the push goes for red
    assert target_choice.chosen_target(layout, target_choice.push(keyframes)) == 0
    assert target_choice.via_stop(layout, keyframes[2:]) is None    # nothing two keyframes before the push
    assert target_choice.via_stop(layout, [[0.02, 0.19, 0.05], hover, down, pushed]) is None  # too low for a stop
    assert target_choice.via_stop(layout, keyframes[:3]) is None    # no push
