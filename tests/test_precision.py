"""Insertion on the real simulator: the planner's cloud never blocks the robot's own start, a pose just
beyond the arm's reach is approached as near as the arm goes, collision flags mean the same thing in
every demo, and every failed episode gets one reason."""

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rvt2cli.data.keyframes import Keyframe
from rvt2cli.eval.executor import CLEARANCE, COLLISION_RESOLUTION, REACH_SLACK_M, Executor
from rvt2cli.eval.journal import read_journal
from rvt2cli.eval.robot_geometry import RobotGeometry
from rvt2cli.eval.rollout import _collision_points
from rvt2cli.eval.sources import OracleSource
from rvt2cli.eval.taxonomy import REASONS, STALL_REPEATS, count_reasons, failure_reason, stalled
from rvt2cli.keyframes.extract import label_keyframes
from rvt2cli.record.expert import run_expert
from rvt2cli.record.capture import capture_cameras
from rvt2cli.record.scene import held_objects, make_env, segmentation_ids
from rvt2cli.robot import RobotFacts
from rvt2cli.runtime import seed_everything
from rvt2cli.tasks import get_task

# a policy's 400 episodes (8 tasks, results v2), recorded on a GPU machine
V2_JOURNAL = Path(__file__).resolve().parent / "fixtures" / "journals" / "eight_tasks_v2.jsonl"
RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


@pytest.fixture(scope="module")
def peg_env():
    env = make_env(get_task("insert_peg"))
    yield env
    env.close()


def _colliding_links(executor: Executor, points: np.ndarray) -> set[str]:
    executor.planner.update_point_cloud(points, radius=COLLISION_RESOLUTION)
    return {c.link_name1 for c in executor.planner.check_for_env_collision(qpos=executor.qpos(), with_point_cloud=True)}


def test_the_robot_geometry_clears_exactly_the_points_its_faces_define():
    """`RobotGeometry.near` tests a hull's faces only on the points in a ball around the padded hull.
    On the Panda's own collision hulls, each link at a random pose, it marks the same points as testing
    every point against every face: those below `pad` above all the faces of some hull."""
    import mani_skill

    urdf = Path(mani_skill.__file__).parent / "assets" / "robots" / "panda" / "panda_v2.urdf"
    geometry = RobotGeometry.from_urdf(urdf, "panda_joint7")
    rng = np.random.default_rng(0)
    poses = {}
    for name in geometry.hulls:
        pose = np.eye(4)
        pose[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        pose[:3, 3] = rng.uniform(-0.3, 0.3, 3)
        poses[name] = pose
    around_links = np.concatenate([pose[:3, 3] + rng.normal(0, 0.06, (4000, 3)) for pose in poses.values()])
    points = np.concatenate([around_links, rng.uniform(-0.6, 0.6, (20_000, 3))])
    for pad in (0.0, CLEARANCE, 0.05):
        every_face = np.zeros(len(points), dtype=bool)
        for name, pose in poses.items():
            for hull in geometry.hulls[name]:
                local = (points - pose[:3, 3]) @ pose[:3, :3]
                every_face |= (local @ hull.planes[:, :3].T + hull.planes[:, 3]).max(axis=1) < pad
        assert 0.05 < every_face.mean() < 0.9  # the test is not trivial either way
        np.testing.assert_array_equal(geometry.near(points, poses, pad), every_face)


@pytest.mark.sim
def test_the_robot_never_blocks_its_own_plan(peg_env):
    """The case of the logs: the peg pushed into the box, the wrist camera's housing over the box's
    points. The raw cloud puts the start state in collision; the cleared one does not, and the retreat
    plans with the cloud (no fallback)."""
    task, seed = get_task("insert_peg"), 10000
    oracle = OracleSource(peg_env)
    seed_everything(seed)
    oracle.reset(task, seed, "")
    seed_everything(seed)
    peg_env.reset(seed=seed)
    executor = Executor(peg_env, 10_000, task.planner_speed, task.gripper_close)
    insertion = next(i for i, k in enumerate(oracle.queue) if k.ignore_collisions and not k.gripper_open and i > 1)
    for keyframe in oracle.queue[:insertion + 1]:
        assert executor.execute(keyframe).reached
    assert held_objects(peg_env) == {"peg"}
    segmentation: dict = {}
    frames = capture_cameras(peg_env, segmentation)
    peg_ids = segmentation_ids(peg_env, {"peg"}, include_robot=False)
    assert len(peg_ids) == 1 and any(np.isin(s, peg_ids).any() for s in segmentation.values())  # the peg is seen...
    points = _collision_points(peg_env, frames, segmentation, task.scene_bounds)
    peg = peg_env.unwrapped.peg.pose.p[0].numpy()
    # ...and left out: no point within the peg's half-width of its centre (the box's hole is wider)
    assert np.linalg.norm(points - peg, axis=1).min() > 0.5 * float(peg_env.unwrapped.peg_half_sizes[0, 1])
    retreat = Keyframe.from_pose([*(np.asarray(oracle.queue[insertion].position) + [0, 0, 0.05]), *oracle.queue[insertion].quaternion],
                                 gripper_open=True, ignore_collisions=False)
    assert "camera_link" in _colliding_links(executor, points)      # the log's "camera_link and point_cloud collide"
    assert _colliding_links(executor, executor.clear_cloud(points, retreat)) == set()
    reach = executor.execute(retreat, points)
    assert reach.reached and not reach.collision_fallback and not reach.start_in_collision, reach


@pytest.mark.sim
def test_a_pose_just_beyond_reach_is_approached_as_near_as_the_arm_goes(peg_env):
    """A grasp the policy of results v2 predicted 9 mm beyond the arm's reach (insert_peg, seed 10007):
    the executor goes to the nearest pose and reports the distance; a pose metres away stays unreachable."""
    record = next(r for line in V2_JOURNAL.read_text().splitlines()[1:]
                  if (r := json.loads(line))["task"] == "insert_peg" and r["seed"] == 10007)
    seed_everything(record["seed"])
    peg_env.reset(seed=record["seed"])
    task = get_task("insert_peg")
    executor = Executor(peg_env, 10_000, task.planner_speed, task.gripper_close)
    above, grasp = (Keyframe.from_pose(s["target"], s["gripper_open"], s["ignore_collisions"]) for s in record["steps"][:2])
    assert record["steps"][1]["reached"] is False                    # what the v2 executor made of it
    assert executor.execute(above).reached
    reach = executor.execute(grasp)
    assert reach.reached and reach.nearest and 1.0 < reach.position_error_mm < 1000 * REACH_SLACK_M, reach
    far = executor.execute(Keyframe.from_pose([2.0, 2.0, 2.0, 0, 1, 0, 0], gripper_open=True, ignore_collisions=True))
    assert not far.reached and far.why == "no_ik"


@pytest.mark.sim
def test_collision_flags_mean_the_same_thing_in_every_demo():
    """plug_charger seeds 2 and 6: the expert slid the charger in without touching the receptacle, so
    contacts alone labelled the insertion collision-avoiding; ending 0.1 mm from the walls, it is
    collision-ignoring, as in the demos that touched. The grasp too, touching or not."""
    task = get_task("plug_charger")
    env = make_env(task, cameras=("front",), image_size=32)
    facts = RobotFacts.from_agent(env.unwrapped.agent)
    try:
        for seed in (2, 6):
            frames = run_expert(env, task.expert, seed, max_frames=task.max_steps).frames
            args = ([f.gripper_command for f in frames],
                    facts.arm(np.array([f.state["joint_velocities"] for f in frames]), frames[0].state["joint_names"]),
                    [f.contacts for f in frames], [f.state["tcp_pose"] for f in frames])
            by_contacts = label_keyframes(*args)
            keyframes = label_keyframes(*args, near=[f.near for f in frames])
            assert not by_contacts[-1].ignore_collisions and keyframes[-1].ignore_collisions, seed
            grasp = next(k for k in keyframes if "gripper" in k.reasons)
            assert grasp.ignore_collisions, seed
    finally:
        env.close()


def test_recorded_episodes_carry_what_is_near_the_robot(tiny_dataset):
    from rvt2cli.data import read_episode
    from rvt2cli.data.paths import episode_paths

    episode = read_episode(episode_paths([str(tiny_dataset)])[0])
    near = episode.robot.near
    assert near is not None and len(near) == len(episode.robot)
    assert all(set(c) <= set(n) for c, n in zip(episode.robot.contacts, near))   # touching is near
    assert any(set(n) - set(c) for c, n in zip(episode.robot.contacts, near))    # and near is more than touching


def test_every_failed_episode_of_a_recorded_journal_has_one_reason():
    records = [json.loads(line) for line in V2_JOURNAL.read_text().splitlines()[1:]]
    for task in {r["task"] for r in records}:
        mine = [r for r in records if r["task"] == task]
        insertion = get_task(task).insertion
        reasons = [failure_reason(r, insertion) for r in mine]
        assert all((reason is None) == r["success"] for r, reason in zip(mine, reasons))
        assert all(reason is None or reason in REASONS for reason in reasons)
        assert sum(count_reasons(mine, insertion).values()) == sum(not r["success"] for r in mine)
        for r, reason in zip(mine, reasons):
            if r["failure"] == "planning_failure":
                assert reason.startswith("unreachable_")  # that journal's executor had no nearest pose
            if r["failure"] == "budget_exhausted" and not insertion:
                assert reason == ("stalled" if stalled(r["steps"]) else "budget_spent")


def test_a_policy_that_repeats_the_pose_it_reached_has_stalled():
    """rvt2-18's stack_cups seed 10007 (the published evaluation): the second cup set down 7 cm from the
    base, then 14 keyframes where the arm already was until the keyframe budget ran out: `stalled`. The same
    record whose last keyframes kept moving 2 cm each, or closed and opened the gripper, spent its budget otherwise."""
    journal = RESULTS / "stage2_min_points_h200x2" / "eval_all18_min200" / "episodes.jsonl.xz"
    record = next(r for r in read_journal(journal)[1] if r["task"] == "stack_cups" and r["seed"] == 10007)
    assert record["failure"] == "budget_exhausted" and len(record["steps"]) == 25
    assert failure_reason(record, insertion=False) == "stalled"
    moving = copy.deepcopy(record)
    for k, step in enumerate(moving["steps"][-STALL_REPEATS - 1:]):
        step["target"][0] += 0.02 * k
    assert failure_reason(moving, insertion=False) == "budget_spent"
    regripped = copy.deepcopy(record)
    regripped["steps"][-3]["gripper_open"] = not regripped["steps"][-3]["gripper_open"]  # closed, then open again
    assert failure_reason(regripped, insertion=False) == "budget_spent"


def test_replay_bad_input_is_one_line(tmp_path, cli):
    from conftest import assert_one_line_error

    assert_one_line_error(cli("eval", "--replay", tmp_path / "none.jsonl", "--out", tmp_path / "a"), "none.jsonl", "no such")
    (tmp_path / "foreign.jsonl").write_text('{"something": 1}\n')
    assert_one_line_error(cli("eval", "--replay", tmp_path / "foreign.jsonl", "--out", tmp_path / "b"), "foreign.jsonl",
                          "not an rvt2 evaluation journal")
    assert_one_line_error(cli("eval", "--replay", V2_JOURNAL, "--checkpoint", tmp_path, "--out", tmp_path / "c"),
                          "not both")


@pytest.mark.sim
def test_replay_runs_a_recorded_policys_keyframes_through_the_executor(tmp_path):
    from rvt2cli.eval.options import EvalOptions
    from rvt2cli.eval.runner import evaluate

    result = evaluate(EvalOptions(checkpoint=None, replay=str(V2_JOURNAL), tasks=("pick_cube",), episodes=1,
                                  out=str(tmp_path)))
    (replayed,) = result.report["episodes"]
    recorded = next(r for line in V2_JOURNAL.read_text().splitlines()[1:]
                    if (r := json.loads(line))["task"] == "pick_cube" and r["seed"] == 10000)
    assert [s["target"] for s in replayed["steps"]] == [s["target"] for s in recorded["steps"]]
    assert replayed["success"] == recorded["success"]
    assert "replay of" in (tmp_path / "eval.md").read_text()


@pytest.mark.sim
def test_eval_bench_times_the_replayed_episode_and_its_parts(tmp_path):
    """benchmarks/eval_bench.py (docs/BENCHMARKS.md, "Evaluation"): the same replay, from a journal compressed
    as published ones are (xz), timed in one process, its time split into the parts of an episode."""
    import lzma
    import subprocess
    import sys

    journal = tmp_path / "episodes.jsonl.xz"
    journal.write_bytes(lzma.compress(V2_JOURNAL.read_bytes()))
    out = tmp_path / "bench.json"
    run = subprocess.run([sys.executable, "-m", "benchmarks.eval_bench", str(journal), "--tasks", "pick_cube", "--episodes", "1",
                          "--json", str(out)], capture_output=True, text=True, cwd=Path(__file__).resolve().parent.parent)
    assert run.returncode == 0, run.stderr
    bench = json.loads(out.read_text())
    (episode,) = bench["episodes"]
    recorded = next(r for line in V2_JOURNAL.read_text().splitlines()[1:]
                    if (r := json.loads(line))["task"] == "pick_cube" and r["seed"] == 10000)
    assert (episode["task"], episode["seed"], episode["success"]) == ("pick_cube", 10000, recorded["success"])
    parts = bench["parts_s"]
    assert parts["render the cameras"] > 0 and parts["simulate (control steps)"] > 0
    assert sum(parts.values()) <= bench["seconds"] * 1.01 and bench["seconds"] >= episode["seconds"]
    assert "| pick_cube | 1 |" in run.stdout
