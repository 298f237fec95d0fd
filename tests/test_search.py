"""The insertion search on the real simulator: a policy's insertion that stopped at the box's face beside
the hole finds it, one that went in is left as it was, and without the search the executor is the one that
recorded the journal."""

import json
from pathlib import Path

import numpy as np
import pytest

from rvt2cli.errors import UserError
from rvt2cli.eval.journal import read_journal
from rvt2cli.eval.options import EvalOptions
from rvt2cli.eval.search import MAX_PROBES, RETRACT_M, InsertionSearch, across
from rvt2cli.tasks import _parse, get_task

JOURNALS = Path(__file__).resolve().parent / "fixtures" / "journals"
# 50 insert_peg episodes of a one-task policy (results v8), recorded on a GPU machine without the search
V8_PEG = JOURNALS / "insert_peg_one_task_pushed_straight.jsonl"
# the two insertions of the 8-task model of results v11, recorded on a GPU machine with v11's search grids
V11_INSERTIONS = JOURNALS / "insertions_8_tasks_v11_grids.jsonl"


def _recorded(seed: int, journal: Path = V8_PEG, task: str = "insert_peg") -> dict:
    """The recorded episode of `task` with this seed in an evaluation journal."""
    return next(r for r in read_journal(journal)[1] if r["task"] == task and r["seed"] == seed)


def _replay(seed: int, out: Path, search: bool = True, step_budget_scale: float = 2.0):
    from rvt2cli.eval.runner import evaluate

    result = evaluate(EvalOptions(checkpoint=None, replay=str(V8_PEG), tasks=("insert_peg",), episodes=1, seed=seed,
                                  out=str(out), insertion_search=search, step_budget_scale=step_budget_scale))
    (record,) = result.report["episodes"]
    return result, record


def test_the_probes_spiral_out_from_the_keyframes_line_on_the_grid():
    pitch = 0.004
    offsets = InsertionSearch(pitch).offsets()
    assert offsets.shape == (MAX_PROBES, 2)
    assert np.array_equal(offsets[0], [0, 0])                        # the keyframe's own line first
    radii = np.hypot(offsets[:, 0], offsets[:, 1])
    assert np.all(np.diff(radii) >= -1e-12)                          # then ring by ring, outwards
    assert np.allclose(np.sort(radii[1:5]), pitch)                  # the four nearest grid points
    assert np.allclose(offsets / pitch, np.round(offsets / pitch))   # on the grid
    assert len(np.unique(np.round(offsets / pitch), axis=0)) == MAX_PROBES
    for direction in ([0, 1, 0], [0, 0, -1], np.array([1, 2, -0.5]) / np.linalg.norm([1, 2, -0.5])):
        plane = across(np.asarray(direction, float))
        assert np.allclose(plane @ plane.T, np.eye(2)) and np.allclose(plane @ direction, 0)


def test_a_task_gives_its_search_pitch_or_none():
    assert InsertionSearch.for_task(get_task("insert_peg")).pitch_m == pytest.approx(get_task("insert_peg").search_pitch_mm / 1000)
    assert InsertionSearch.for_task(get_task("stack_cube")) is None
    base = 'name = "t"\nenv_id = "PegInsertionSide-v1"\nexpert = "m:f"\ninstructions = ["x"]\nmax_steps = 10\n'
    with pytest.raises(UserError, match="search_pitch_mm must be a number >= 0"):
        _parse(base + "search_pitch_mm = -1\n", "tasks/t.toml")
    # each probe backs off the task's retract (4 mm unless the task gives one)
    assert InsertionSearch.for_task(get_task("insert_peg")).retract_m == pytest.approx(RETRACT_M)
    assert _parse(base + "search_pitch_mm = 1\nsearch_retract_mm = 1.5\n", "tasks/t.toml").search_retract_mm == 1.5
    with pytest.raises(UserError, match="search_retract_mm must be a number > 0"):
        _parse(base + "search_pitch_mm = 1\nsearch_retract_mm = 0\n", "tasks/t.toml")


@pytest.mark.sim
def test_an_insertion_stopped_at_the_face_finds_the_hole(tmp_path):
    """Seed 10012: the policy's insertion puts the peg's head 4 mm beside the hole (3 mm of clearance).
    Pushed straight, as when it was recorded, the peg stops at the face and the episode fails; with the
    search, a probe a grid step away goes in."""
    recorded = _recorded(10012)
    off, straight = _replay(10012, tmp_path / "off", search=False)
    assert not recorded["success"] and not straight["success"]
    assert straight["control_steps"] == recorded["control_steps"]        # the executor that recorded it
    assert all(s["probes"] == 0 for s in straight["steps"])
    assert "Insertion search off" in (tmp_path / "off" / "eval.md").read_text()

    on, searched = _replay(10012, tmp_path / "on")
    assert searched["success"]
    insertion = searched["steps"][-1]
    assert insertion["ignore_collisions"] and not insertion["gripper_open"] and insertion["held"]
    assert insertion["probes"] >= 1 and 0 < insertion["search_offset_mm"] <= 2 * np.sqrt(2) * get_task("insert_peg").search_pitch_mm
    assert [s["target"] for s in searched["steps"]] == [s["target"] for s in recorded["steps"][: len(searched["steps"])]]
    assert on.report["tasks"]["insert_peg"]["policy"]["insertion_search"] == {"searched": 1, "found": 1,
                                                                               "probes": insertion["probes"]}
    assert "found the hole, of those searched: insert_peg policy: 1 of 1" in (tmp_path / "on" / "eval.md").read_text()


@pytest.mark.sim
def test_an_insertion_that_goes_in_is_not_searched(tmp_path):
    """Seed 10024: the policy's first insertion went in. With the search on, nothing changes: no probe,
    the same control steps as recorded."""
    recorded = _recorded(10024)
    _, replayed = _replay(10024, tmp_path)
    assert recorded["success"] and replayed["success"]
    assert replayed["control_steps"] == recorded["control_steps"]
    assert all(s["probes"] == 0 for s in replayed["steps"])


@pytest.mark.sim
def test_a_search_cut_short_by_the_budget_is_kept_in_the_journal(tmp_path):
    """Seed 10012 again, with 130 control steps: they run out while the search probes. The insertion is
    still in the journal, marked interrupted with its probes, so the failure reads as an insertion short
    of the hole, not as no attempt; its arm was not at rest, so the errors at rest leave it out."""
    from rvt2cli.eval.taxonomy import failure_reason

    result, record = _replay(10012, tmp_path, step_budget_scale=130 / get_task("insert_peg").max_steps)
    assert not record["success"] and record["failure"] == "budget_exhausted" and record["control_steps"] == 130
    last = record["steps"][-1]
    assert last["interrupted"] and last["probes"] >= 1 and last["ignore_collisions"] and last["held"]
    assert not any(s["interrupted"] for s in record["steps"][:-1])
    assert failure_reason(record, insertion=True) == "insertion_short"
    assert result.report["tasks"]["insert_peg"]["policy"]["pose_error"]["keyframes"] == len(record["steps"]) - 1  # not at rest


@pytest.mark.sim
def test_pushed_straight_the_peg_stops_at_the_face_and_slides_back_in_the_fingers():
    """rvt2 diagnose insertion-stops on seed 10012: the first insertion leaves the peg's head at the box's
    face, 4 mm across the hole's axis, and the push slid the peg centimetres back through the fingers."""
    from rvt2cli.diagnose.insertion_stops import first_insertion, first_insertion_stop

    recorded = _recorded(10012)
    assert first_insertion(recorded["steps"]) == 3
    stop = first_insertion_stop(recorded)
    assert not stop["went_in"] and 3 < stop["across_mm"] < 5
    assert stop["head_mm"][0] < -80           # at the face: success needs the head within 15 mm of the hole's centre
    assert stop["slid_back_mm"] > 30


@pytest.mark.sim
def test_the_charger_starts_its_push_off_the_axis_and_pivots_at_the_face():
    """rvt2 diagnose insertion-stops --task plug_charger on seed 10001 of the 8-task model of results v11:
    where the push starts, the charger is millimetres across the receptacle's axis (0.5 mm of clearance)
    and turned; pushed straight it stops at the face and pivots in the fingers."""
    from rvt2cli.diagnose.insertion_stops import first_insertion, first_insertion_stop

    recorded = _recorded(10001, V11_INSERTIONS, "plug_charger")
    assert first_insertion(recorded["steps"]) == 3
    stop = first_insertion_stop(recorded)
    assert not stop["went_in"]
    assert 3 < stop["across_mm"] < 4.5 and stop["turn_deg"] > 4 and stop["offset_mm"][0] < -40   # before the face
    after = stop["after"]
    assert after["offset_mm"][0] > -25 and after["turn_deg"] > stop["turn_deg"] + 3             # at it, pivoted


@pytest.mark.sim
def test_the_chargers_wider_grid_reaches_a_receptacle_the_v11_grid_could_not(tmp_path):
    """Seed 10012 of the 8-task model of results v11, recorded with plug_charger's 0.5 mm grid and 4 mm
    retract: its 37 probes, all within 1.8 mm of the keyframe's line, found nothing before the control steps
    ran out. Its keyframes through today's grid (1 mm, 1.5 mm retract): a probe further out goes in."""
    from rvt2cli.eval.runner import evaluate

    recorded = _recorded(10012, V11_INSERTIONS, "plug_charger")
    old_reach = 1000 * np.hypot(*InsertionSearch(0.0005).offsets().T).max()
    assert not recorded["success"] and recorded["failure"] == "budget_exhausted"
    assert recorded["steps"][-1]["probes"] > 30 and old_reach < 2
    result = evaluate(EvalOptions(checkpoint=None, replay=str(V11_INSERTIONS), tasks=("plug_charger",), episodes=1, seed=10012,
                                  out=str(tmp_path)))
    (record,) = result.report["episodes"]
    assert record["success"]
    insertion = record["steps"][-1]
    assert insertion["probes"] >= 1 and insertion["search_offset_mm"] > old_reach
    assert result.report["search_grids"] == {"plug_charger": {"pitch_mm": 1.0, "retract_mm": 1.5}}
    assert "grid 1 mm, retract 1.5 mm" in (tmp_path / "eval.md").read_text()


def test_an_evaluation_begun_before_the_search_resumes_only_pushed_straight(tmp_path):
    """A journal of an earlier rvt2 has no insertion_search in its plan: it was pushed straight. Resuming
    it with the search is refused in one line, before any episode runs."""
    from rvt2cli.eval.runner import evaluate

    options = EvalOptions(checkpoint=None, replay=str(V8_PEG), tasks=("insert_peg",), episodes=1, seed=10012,
                          out=str(tmp_path), resume=True)
    plan = options.plan(f"replay of {V8_PEG}")
    del plan["insertion_search"]
    (tmp_path / "episodes.jsonl").write_text(json.dumps({"rvt2_eval_journal": 1, "plan": plan}) + "\n")
    with pytest.raises(UserError, match="was run with insertion_search = False, this command has True"):
        evaluate(options)
