"""`rvt2 eval`: the executor reaches recorded keyframes (oracle), and a trained checkpoint runs end to end."""

import json

import pytest

from conftest import assert_one_line_error
from rvt2cli.eval.runner import EvalOptions, evaluate

pytestmark = pytest.mark.sim


def test_oracle_on_recorded_demos_succeeds(tiny_dataset, tmp_path):
    result = evaluate(EvalOptions(checkpoint=None, oracle=True, demos=(str(tiny_dataset),), out=str(tmp_path)))
    outcomes = [o for _, o in result.outcomes]
    assert [o.seed for o in outcomes] == [0, 1]
    assert all(o.success for o in outcomes), [(o.failure, [s.reached for s in o.steps]) for o in outcomes]
    assert result.report["tasks"]["stack_cube"]["oracle"]["success_rate"] == 1.0


def test_eval_with_a_checkpoint_writes_every_output(tiny_checkpoint, tmp_path, cli):
    run_dir, _ = tiny_checkpoint
    out = tmp_path / "eval"
    r = cli("eval", "--checkpoint", run_dir, "--episodes", "1", "--keyframe-budget", "3", "--video", "--save-rollouts",
            "--out", out)
    assert r.returncode == 0, r.stderr
    report = json.loads((out / "eval.json").read_text())
    episode = report["episodes"][0]
    assert episode["task"] == "stack_cube" and episode["seed"] == 10000 and episode["source"] == "policy"
    assert 1 <= episode["keyframes"] <= 3
    assert episode["success"] or episode["failure"] in ("planning_failure", "budget_exhausted", "task_failed")
    assert "stack_cube" in (out / "eval.md").read_text()
    assert (out / "eval.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "videos" / "policy_stack_cube_10000.mp4").stat().st_size > 1000
    assert (out / "rollouts" / "policy_stack_cube_10000.mcap").stat().st_size > 100


def test_eval_refuses_missing_and_foreign_checkpoints(tmp_path, cli):
    assert_one_line_error(cli("eval", "--checkpoint", tmp_path / "nope"), "nope", "no such checkpoint")
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "config.json").write_text("{}")
    (tmp_path / "foreign" / "model.safetensors").write_bytes(b"")
    assert_one_line_error(cli("eval", "--checkpoint", tmp_path / "foreign"), "foreign", "not an rvt2 checkpoint")
