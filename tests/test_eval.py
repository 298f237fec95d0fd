"""`rvt2 eval`: the executor reaches recorded keyframes (oracle), and a trained checkpoint runs end to end."""

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_one_line_error
from rvt2cli.eval.runner import EvalOptions, evaluate
from rvt2cli.record.robot_visuals import DESCRIPTION as ROBOT_VISUALS

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


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="needs a machine without a GPU")
def test_cuda_without_gpu_is_refused_before_any_simulator_starts(tiny_checkpoint, tmp_path, cli):
    r = cli("eval", "--checkpoint", tiny_checkpoint, "--episodes", "1", "--device", "cuda", "--out", tmp_path / "e")
    assert_one_line_error(r, "--device cuda", "no CUDA GPU", "--device cpu")
    assert not (tmp_path / "e").exists()


def test_a_report_of_no_finished_episode_is_written_without_a_chart(tmp_path):
    """Simulators that die before any episode ends still leave a report (of nothing) behind the one-line error."""
    from rvt2cli.eval.report import build_report, write_report
    from rvt2cli.eval.runner import report_meta

    write_report(build_report([], report_meta(EvalOptions(checkpoint="c", episodes=1), "c", ["insert_peg"], [], 0.0)), tmp_path)
    assert json.loads((tmp_path / "eval.json").read_text())["episodes"] == []
    assert (tmp_path / "eval.md").exists() and not (tmp_path / "eval.png").exists()


def test_oracle_report_carries_pose_errors_at_rest(tmp_path):
    """One oracle episode of insert_peg: every keyframe's error at rest is in eval.json and eval.md."""
    result = evaluate(EvalOptions(checkpoint=None, oracle=True, tasks=("insert_peg",), episodes=1, out=str(tmp_path)))
    summary = result.report["tasks"]["insert_peg"]["oracle"]
    pose = summary["pose_error"]
    assert pose["keyframes"] >= 4
    assert 0 <= pose["position_mm"]["median"] < 0.5 and 0 <= pose["rotation_deg"]["median"] < 0.3
    steps = result.report["episodes"][0]["steps"]
    assert all(s["position_error_mm"] is not None for s in steps if s["reached"])
    assert "error at rest" in (tmp_path / "eval.md").read_text()
    free, contact = summary["pose_error_free"], summary["pose_error_contact"]
    assert free["keyframes"] + contact["keyframes"] == pose["keyframes"] and free["keyframes"] >= 3
    assert free["position_mm"]["p95"] < 0.5 and free["rotation_deg"]["p95"] < 0.3  # free space: the goal
    assert "keyframes in free space" in (tmp_path / "eval.md").read_text()
    episode = result.report["episodes"][0]
    assert episode["step_budget"] == 2 * episode["task_max_steps"] == 800  # the default --step-budget-scale


def test_untrained_task_is_warned_in_one_line_and_noted(tiny_checkpoint, tmp_path, cli):
    run_dir, _ = tiny_checkpoint
    r = cli("eval", "--checkpoint", run_dir, "--tasks", "push_cube", "--episodes", "1", "--keyframe-budget", "1",
            "--out", tmp_path, "--no-progress")
    assert r.returncode == 0, r.stderr[-2000:]
    warnings = [line for line in r.stderr.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "push_cube" in warnings[0] and "training set" in warnings[0], r.stderr
    assert json.loads((tmp_path / "eval.json").read_text())["untrained_tasks"] == ["push_cube"]
    assert "generalisation test" in (tmp_path / "eval.md").read_text()


def test_a_checkpoint_knows_its_demos_renderer_robot_meshes_and_phrasing_and_eval_warns_under_others(tiny_checkpoint, tmp_path, cli):
    import shutil

    from rvt2cli.runtime import use_vulkan_driver

    run_dir, _ = tiny_checkpoint
    here = use_vulkan_driver().name
    configs = sorted(Path(run_dir).rglob("config.json"))
    rigs = json.loads(configs[0].read_text())["rigs"]
    assert {rig["renderer"] for rig in rigs.values()} == {here}   # recorded in the demos, kept by training
    assert {rig["robot_visuals"] for rig in rigs.values()} == {ROBOT_VISUALS}
    other = "nvidia" if here != "nvidia" else "lavapipe"
    elsewhere = tmp_path / "run"
    shutil.copytree(run_dir, elsewhere)
    for config in elsewhere.rglob("config.json"):
        data = json.loads(config.read_text())
        for rig in data["rigs"].values():
            rig["renderer"] = other
            del rig["robot_visuals"]   # as demos recorded before the Panda was lightened
        data["options"]["phrasings"] = "first"   # as `rvt2 train --phrasings first` keeps it
        config.write_text(json.dumps(data))
    r = cli("eval", "--checkpoint", elsewhere, "--episodes", "1", "--keyframe-budget", "1", "--out", tmp_path / "ev",
            "--no-progress")
    assert r.returncode == 0, r.stderr[-2000:]
    warnings = [line for line in r.stderr.splitlines() if "warning" in line.lower()]
    assert len(warnings) == 3 and f"rendered by {other}" in warnings[0] and f"renders with {here}" in warnings[0], r.stderr
    assert "first phrasing alone" in warnings[1] and "give --first-phrasing" in warnings[1], r.stderr
    assert "drew the Panda with ManiSkill's full meshes" in warnings[2] and ROBOT_VISUALS in warnings[2], r.stderr


def test_a_crashed_worker_keeps_the_finished_episodes_and_resume_runs_the_rest(tmp_path):
    """A simulator process killed mid-run (as a native crash would end it): the finished episodes are
    in the journal, the command says so in one line, and --resume completes the evaluation."""
    import os
    import signal
    import subprocess
    import sys
    import time

    import psutil

    out = tmp_path / "eval"
    argv = [sys.executable, "-m", "rvt2cli", "eval", "--oracle", "--tasks", "push_cube", "--episodes", "6", "--workers", "2",
            "--out", str(out), "--no-progress"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    journal = out / "episodes.jsonl"
    deadline = time.time() + 600
    while time.time() < deadline and proc.poll() is None:
        if journal.exists() and len(journal.read_text().splitlines()) >= 2:  # header + one finished episode
            break
        time.sleep(0.2)
    workers = [c for c in psutil.Process(proc.pid).children(recursive=True) if "spawn_main" in " ".join(c.cmdline())]
    assert workers, "no worker process to kill"
    os.kill(workers[0].pid, signal.SIGKILL)
    _, stderr = proc.communicate(timeout=600)
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "--resume" in lines[0] and "Traceback" not in stderr, stderr
    kept = [json.loads(line) for line in journal.read_text().splitlines()[1:]]
    assert 1 <= len(kept) < 6
    r = subprocess.run(argv + ["--resume"], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    report = json.loads((out / "eval.json").read_text())
    assert sorted(e["seed"] for e in report["episodes"]) == list(range(10000, 10006))
    assert [json.loads(line) for line in journal.read_text().splitlines()[1:len(kept) + 1]] == kept  # not run again


def test_eval_without_resume_refuses_a_folder_with_an_evaluation(tmp_path, cli):
    (tmp_path / "episodes.jsonl").write_text('{"rvt2_eval_journal": 1, "plan": {}}\n')
    assert_one_line_error(cli("eval", "--oracle", "--tasks", "push_cube", "--episodes", "1", "--out", tmp_path),
                          "holds an evaluation already", "--resume")


def test_offline_precision_of_a_checkpoint_on_recorded_demos(tiny_checkpoint, tiny_dataset, tmp_path, cli):
    run_dir, _ = tiny_checkpoint
    out = tmp_path / "offline"
    r = cli("eval", "--checkpoint", run_dir, "--offline", tiny_dataset, "--out", out, "--no-progress")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "stage-2 error" in r.stdout
    report = json.loads((out / "offline.json").read_text())
    stack = report["tasks"]["stack_cube"]
    assert stack["samples"] == report["overall"]["samples"] > 10
    assert stack["stage2_mm"]["median"] < 10.0 and stack["stage2_mm"]["p90"] >= stack["stage2_mm"]["median"]  # trained on them
    assert stack["gripper_accuracy"] >= 0.9
    assert set(stack["keyframes"]) >= {"0", "1"} and "stage 2 mm" in (out / "offline.md").read_text()
    # the observations a closed loop makes: frame 0 and each keyframe's frame, one per keyframe of each demo
    from rvt2cli.data import read_episode
    from rvt2cli.data.paths import episode_paths

    annotations = [read_episode(p).require_keyframes() for p in episode_paths([str(tiny_dataset)])]
    assert stack["starts"]["samples"] == sum(len(a.keyframes) for a in annotations) < stack["samples"]
    assert sum(s["samples"] for s in stack["start_keyframes"].values()) == stack["starts"]["samples"]
    assert "| starts |" in (out / "offline.md").read_text() and "| 1 start |" in (out / "offline.md").read_text()


def test_stage_2s_box_at_keyframe_starts_and_stage_1s_point_kept_below_a_count(tiny_checkpoint, tiny_dataset):
    """rvt2 diagnose stage2-blind on the tiny checkpoint: one row per keyframe start, each box's count, and the
    kept error equal to stage 1's exactly where the count is below the threshold."""
    from rvt2cli.diagnose import stage2_blind
    from rvt2cli.data import read_episode
    from rvt2cli.data.paths import episode_paths

    rows = stage2_blind.keyframe_starts(str(tiny_checkpoint[0]), [str(tiny_dataset)])
    annotations = [read_episode(p).require_keyframes() for p in episode_paths([str(tiny_dataset)])]
    assert len(rows) == sum(len(a.keyframes) for a in annotations)
    assert all(r["task"] == "stack_cube" and r["points"] >= 0 for r in rows)
    threshold = int(np.median([r["points"] for r in rows])) + 1
    kept = stage2_blind.with_min_points(rows, threshold)
    assert any(r["points"] < threshold for r in rows) and any(r["points"] >= threshold for r in rows)
    assert all(k["kept_mm"] == (k["stage1_mm"] if k["points"] < threshold else k["stage2_mm"]) for k in kept)
    assert stage2_blind.table(kept, threshold)[-1].startswith("| **all** |")


def test_diagnose_prints_its_table_and_writes_its_report(tiny_checkpoint, tiny_dataset, tmp_path, cli):
    """`rvt2 diagnose stage2-blind` through the command line: the table on stdout, the report with every row and
    the software that made it in --json (its folder made); bad input is one line."""
    out = tmp_path / "reports" / "blind.json"
    r = cli("diagnose", "stage2-blind", "--checkpoint", tiny_checkpoint[0], tiny_dataset, "--min-points", "50", "--json", out)
    assert r.returncode == 0, r.stderr
    report = json.loads(out.read_text())
    assert report["diagnostic"] == "stage2-blind" and report["min_points"] == 50 and "torch" in report["software"]
    assert report["table"][-1] in r.stdout and {row["task"] for row in report["rows"]} == {"stack_cube"}
    assert_one_line_error(cli("diagnose", "target-choice", tmp_path / "missing.jsonl"), "missing.jsonl", "episodes.jsonl")
    assert_one_line_error(cli("diagnose", "precision-budget", "--variants", "rot72,sideways"), "'sideways'", "rotN")
    r = cli("diagnose")   # no NAME: the list of diagnostics
    assert r.returncode == 2 and "precision-budget" in r.stderr and "target-choice" in r.stderr


def test_offline_bad_input_is_one_line(tiny_checkpoint, tmp_path, cli):
    from rvt2cli.record.recorder import RecordOptions, record

    run_dir, _ = tiny_checkpoint
    record("stack_cube", 1, tmp_path / "raw", options=RecordOptions(cameras=("front", "left_shoulder", "right_shoulder"),
                                                                    image_size=32, keyframes=False))
    assert_one_line_error(cli("eval", "--checkpoint", run_dir, "--offline", tmp_path / "raw"), "no keyframes", "extract-keyframes")
    assert_one_line_error(cli("eval", "--checkpoint", run_dir, "--offline", tmp_path / "raw", "--first-phrasing"),
                          "eval --offline scores each demo under the words its checkpoint was trained to read", "--first-phrasing")
    record("push_cube", 1, tmp_path / "other", options=RecordOptions(cameras=("front",), image_size=32))
    assert_one_line_error(cli("eval", "--checkpoint", run_dir, "--offline", tmp_path / "other"), "not trained on task(s) push_cube")


def test_a_cuda_graph_needs_a_checkpoint_on_a_cuda_device(tiny_checkpoint, tmp_path, cli):
    """`--cuda-graph` replays a policy loaded here on a GPU: on the CPU, or beside --shared-policy, one line."""
    run_dir = tiny_checkpoint[0]
    assert_one_line_error(cli("eval", "--checkpoint", run_dir, "--cuda-graph", "--out", tmp_path / "e"),
                          "--cuda-graph", "--device cuda")
    assert_one_line_error(cli("eval", "--checkpoint", run_dir, "--cuda-graph", "--device", "cuda", "--shared-policy",
                              "--workers", "2", "--out", tmp_path / "e"), "--cuda-graph", "without --shared-policy")
    assert not (tmp_path / "e").exists()


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="needs a CUDA device")
def test_on_a_cuda_device_a_graphed_policy_answers_as_the_eager_one(aimed_checkpoint, tmp_path):
    """The replayed graph gives the eager step's keyframe to the bit, for clouds of several sizes (a larger one
    captures the graph again), with and without an aim; and a closed-loop evaluation with --cuda-graph ends every
    episode as the eager one does, keyframe for keyframe."""
    import torch

    from rvt2cli.model.graphed import GraphedPolicy
    from rvt2cli.model.observation import Observation
    from rvt2cli.train.checkpoint import load_policy

    policy, _ = load_policy(aimed_checkpoint, device="cuda")
    graphed = GraphedPolicy(policy)
    cfg, g = policy.cfg, torch.Generator(device="cpu").manual_seed(0)
    for n, aimed in ((9_000, False), (12_000, True), (20_000, False), (3_000, True)):
        obs = Observation(points=torch.rand(1, n, 3, generator=g) * 2 - 1, rgb=torch.rand(1, n, 3, generator=g),
                          num_points=torch.tensor([n]), proprio=torch.rand(1, cfg.proprio_dim, generator=g),
                          lang=torch.randn(1, cfg.lang_tokens, cfg.lang_dim, generator=g),
                          aim=torch.tensor([[0.2, 0.0, 0.05]]) if aimed else None).to("cuda")
        want, got = policy.predict(obs), graphed.predict(obs)
        for field in ("position", "rot_bins", "quaternion", "gripper_open", "ignore_collisions", "stage1_position"):
            assert torch.equal(getattr(want, field), getattr(got, field)), (n, aimed, field)
    assert graphed.predictor.max_points == 32_768  # captured at 16,384, again at 32,768 for 20,000 points

    options = dict(checkpoint=str(aimed_checkpoint), device="cuda", episodes=2, keyframe_budget=3)
    eager = evaluate(EvalOptions(out=str(tmp_path / "eager"), **options))
    replayed = evaluate(EvalOptions(out=str(tmp_path / "graph"), cuda_graph=True, **options))

    def outcomes(result) -> dict:
        return {job: (o.success, o.failure, o.control_steps, [(s.keyframe, s.retry, s.reached) for s in o.steps])
                for job, o in result.outcomes}

    assert outcomes(replayed) == outcomes(eager) and all(o[3] for o in outcomes(eager).values())
    assert replayed.report["cuda_graph"] is True and "CUDA graph" in (tmp_path / "graph" / "eval.md").read_text()
