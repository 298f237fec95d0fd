"""rvt2 diagnose oracle-gap (rvt2cli/diagnose/oracle_gap.py): the expert's keyframes against a policy's nearest, on
the published rvt2-18 journals (the via model's evaluation and the oracle's, seeds 10000-10049)."""

import json

import pytest

from benchmarks.experiment import REPOSITORY
from rvt2cli.diagnose import oracle_gap
from rvt2cli.errors import UserError
from rvt2cli.eval.journal import read_journal

RESULTS = REPOSITORY / "benchmarks" / "results"
ORACLE = RESULTS / "rlbench18_oracle_50" / "episodes.jsonl.xz"
POLICY = RESULTS / "rvt2_18_via_h200x4" / "evals" / "seed0_from10000" / "episodes.jsonl.xz"


def test_the_oracle_as_a_policy_reaches_each_of_its_keyframes(tmp_path):
    plan, records = read_journal(ORACLE)
    journal = tmp_path / "episodes.jsonl"   # the oracle's own episodes, labelled as a policy's
    journal.write_text("\n".join(json.dumps(line) for line in
                                 [{"rvt2_eval_journal": 1, "plan": plan}, *({**r, "source": "policy"} for r in records)]) + "\n")
    report = oracle_gap.report([journal], [ORACLE], tasks=("reach_and_drag", "stack_cups"))
    assert report["episodes"] == 100 and {r["task"] for r in report["rows"]} == {"reach_and_drag", "stack_cups"}
    for row in report["rows"]:
        for part in (row["successes"], row["failures"]):
            assert part["median_mm"] in (None, 0.0) and part["within_near"] == part["episodes"]
            assert part["ahead_median_mm"] in (None, 0.0)
    # the stick's landing (keyframe 4: lift, over the cube, down, drag) carries a held tool; the grasp does not
    landing = next(r for r in report["rows"] if r["task"] == "reach_and_drag" and r["keyframe"] == 4)
    grasp = next(r for r in report["rows"] if r["task"] == "reach_and_drag" and r["keyframe"] == 1)
    assert landing["successes"]["ahead_median_mm"] == 0.0 and grasp["successes"]["ahead_median_mm"] is None


def test_each_task_and_keyframe_of_a_published_evaluation_is_counted_by_outcome():
    report = oracle_gap.report([POLICY], [ORACLE], near_mm=20.0)
    _, episodes = read_journal(POLICY)
    assert report["episodes"] == len(episodes) == 900
    for task in {e["task"] for e in episodes}:
        first = next(r for r in report["rows"] if r["task"] == task and r["keyframe"] == 0)
        mine = [e for e in episodes if e["task"] == task]
        assert first["successes"]["episodes"] == sum(e["success"] for e in mine)
        assert first["failures"]["episodes"] == sum(not e["success"] for e in mine)
    assert all(0 <= r["failures"]["within_near"] <= r["failures"]["episodes"] for r in report["rows"])
    table = oracle_gap.markdown(report)
    assert table.count("\n| reach_and_drag |") == sum(r["task"] == "reach_and_drag" for r in report["rows"])
    # the failed drags bring the stick down ahead of the expert's landing, onto the cube; the successes do not
    landing = next(r for r in report["rows"] if r["task"] == "reach_and_drag" and r["keyframe"] == 4)
    assert landing["failures"]["ahead_median_mm"] > 20 > 10 > landing["successes"]["ahead_median_mm"]


def test_journals_of_other_seeds_are_refused_in_one_line():
    other = RESULTS / "rvt2_18_via_h200x4" / "evals" / "seed0_from10050" / "episodes.jsonl.xz"
    with pytest.raises(UserError, match="rvt2 eval --oracle"):
        oracle_gap.report([other], [ORACLE])
