"""rvt2 diagnose paraphrase-neighbours (rvt2cli/diagnose/paraphrase_neighbours.py): the shipped instruction encoder
on the tasks' own phrasings, no checkpoint."""

import dataclasses

import pytest

from rvt2cli.diagnose import paraphrase_neighbours
from rvt2cli.errors import UserError
from rvt2cli.tasks import get_task


def test_a_trained_phrasing_is_nearest_its_own_variation():
    for name in ("turn_tap", "open_drawer"):
        task = get_task(name)
        as_paraphrases = dataclasses.replace(task, paraphrases=task.instructions)
        rows = paraphrase_neighbours.task_rows(as_paraphrases)
        assert len(rows) == len(task.instructions)
        assert all(r["nearest_own"] == task.num_variations and not r["misplaced"] for r in rows)


def test_each_paraphrase_is_placed_for_every_variation():
    report = paraphrase_neighbours.report(["turn_tap", "open_drawer", "push_cube"])  # push_cube has one variation
    assert report["tasks"] == ["turn_tap", "open_drawer"]
    assert [r["paraphrase"] for r in report["rows"]] == [*get_task("turn_tap").paraphrases, *get_task("open_drawer").paraphrases]
    for row in report["rows"]:
        task = get_task(row["task"])
        assert row["nearest_own"] + len(row["misplaced"]) == row["variations"] == task.num_variations
        for wrong in row["misplaced"]:   # the nearest is a trained phrasing of another variation
            assert wrong["nearest_variation"] != wrong["variation"]
            assert task.variation_of(wrong["nearest"]) == wrong["nearest_variation"]
    table = paraphrase_neighbours.markdown(report)
    assert table.count("\n| turn_tap |") == len(get_task("turn_tap").paraphrases)


def test_tasks_without_paraphrases_are_refused_in_one_line():
    with pytest.raises(UserError, match="paraphrases"):
        paraphrase_neighbours.report(["push_cube"])
