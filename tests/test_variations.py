"""Variations end to end: tasks whose variations only the instruction tells apart, recorded, read back,
evaluated per variation, in the real simulator on real MCAP files (slide_block_to_color_target: 4)."""

import json

import pytest

from conftest import assert_one_line_error
from rvt2cli.data import read_episode, schemas
from rvt2cli.errors import UserError
from rvt2cli.eval.options import EvalOptions
from rvt2cli.eval.rollout import KeyframeSource, run_episode
from rvt2cli.eval.runner import evaluate, plan_jobs
from rvt2cli.eval.sources import expert_keyframes
from rvt2cli.eval.taxonomy import failure_reason
from rvt2cli.record.expert import run_expert
from rvt2cli.record.recorder import RecordOptions, record
from rvt2cli.record.scene import make_env, set_variation, sim_state
from rvt2cli.runtime import use_vulkan_driver
from rvt2cli.tasks import _parse, all_tasks, episode_variation, get_task, task_sets, tasks_of_set

pytestmark = pytest.mark.sim
TASK = "slide_block_to_color_target"
SMALL = RecordOptions(cameras=("front",), image_size=32, obs_every=50)
VARIED = [name for name, task in all_tasks().items() if task.num_variations > 1]


@pytest.fixture(scope="module")
def slide_env():
    env = make_env(get_task(TASK), cameras=("front",), image_size=32)
    yield env
    env.close()


@pytest.fixture(scope="module")
def slide_demos(tmp_path_factory):
    """Four recorded episodes, seeds 0-3: one per variation."""
    out = tmp_path_factory.mktemp("slide")
    summary = record(TASK, 4, out, seed=0, options=SMALL)
    assert summary.counts() == {"success": 4}
    return out


def initial_state(env, seed: int, variation: int) -> dict:
    set_variation(env, variation)
    env.reset(seed=seed)
    return sim_state(env)


@pytest.mark.parametrize("name", VARIED)
def test_a_seed_lays_out_the_same_scene_in_every_variation(name):
    """Only the instruction tells variations apart: a policy that ignores it cannot beat chance."""
    task = get_task(name)
    env = make_env(task, cameras=("front",), image_size=32)
    try:
        assert env.unwrapped.num_variations == task.num_variations, "the TOML's [[variations]] and the env disagree"
        first = initial_state(env, 7, 0)
        for variation in (1, task.num_variations - 1):
            assert initial_state(env, 7, variation) == first
        assert initial_state(env, 8, 0) != first  # the seed, not the variation, lays out the scene
    finally:
        env.close()


def test_slide_block_expert_succeeds_and_the_end_state_fails_the_other_variations(slide_env):
    task = get_task(TASK)
    run = run_expert(slide_env, task.expert, seed=5, max_frames=task.max_steps, variation=2)
    assert run.status == "success" and run.variation == 2
    scene = slide_env.unwrapped
    for other in (0, 1, 3):
        scene.variation = other  # the same end state, judged as another variation's episode
        info = scene.evaluate()
        assert not info["success"].item() and info["wrong_target"].item()
    scene.variation = 2
    assert scene.evaluate()["success"].item() and not scene.evaluate()["wrong_target"].item()


def test_slide_block_reset_refuses_a_variation_it_does_not_have(slide_env):
    with pytest.raises(ValueError, match="variation 4"):
        slide_env.reset(seed=0, options={"variation": 4})
    slide_env.unwrapped.variation = 0


def test_recording_spreads_episodes_over_variations_and_stores_them(slide_demos, cli):
    task = get_task(TASK)
    for seed in range(4):
        ep = read_episode(slide_demos / f"{TASK}_{seed:04d}.mcap")
        assert ep.variation_index == seed and ep.meta.extra["variation"] == seed
        colour = task.variations[seed]["color"]
        assert ep.instruction["variation"] == {"color": colour} and colour in ep.instruction["text"]
        assert ep.instruction["text"] == task.instruction(seed, seed)[0]
        assert ep.format_version == schemas.FORMAT_VERSION
    r = cli("info", "--json", slide_demos / f"{TASK}_0002.mcap")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)[0]
    assert info["variation"] == 2 and info["variation_values"] == {"color": "pink"}
    text = cli("info", slide_demos / f"{TASK}_0002.mcap").stdout
    assert "variation    2  color=pink" in text
    renderer = use_vulkan_driver().name   # the Vulkan driver that drew the cameras, stored with them
    assert info["renderer"] == renderer and f"(rendered by {renderer})" in text


def test_training_samples_carry_their_own_variations_instruction(slide_demos):
    from rvt2cli.data.paths import episode_paths
    from rvt2cli.keyframes.extract import extract_file
    from rvt2cli.train.samples import load_samples

    paths = episode_paths([str(slide_demos)])
    for path in paths:
        extract_file(path)
    samples = load_samples(paths, progress=False, keyframe_starts_only=True)
    for i in range(len(samples)):
        seed = read_episode(samples.episodes[samples.episode_index[i]]).meta.seed
        assert samples.instructions[samples.instruction_index[i]] == get_task(TASK).instruction(seed, seed)[0]
    assert len(set(samples.instruction_index)) == 4


def test_instruction_swap_scores_each_observation_under_every_variations_words(slide_demos, tmp_path):
    """rvt2 diagnose instruction-swap on four real slide_block demos and a policy trained on them briefly: every
    observation is predicted under its own instruction and the three other colours'; the own instruction's
    error is the one `rvt2 eval --offline` measures on the same demos."""
    from conftest import TINY_TRAIN

    from rvt2cli.diagnose.instruction_swap import alternatives, swap_report
    from rvt2cli.data.paths import episode_paths
    from rvt2cli.eval.offline import evaluate_offline
    from rvt2cli.keyframes.extract import extract_file
    from rvt2cli.train.trainer import TrainOptions, train

    own = get_task(TASK).instruction(0, 0)[0]
    swapped = alternatives(TASK, own)
    assert swapped[0] == own and len(set(swapped)) == 4   # the same template in the four colours
    assert alternatives(TASK, "a phrasing the task does not have") == ["a phrasing the task does not have"]
    for path in episode_paths([str(slide_demos)]):
        extract_file(path)
    train(TrainOptions(data=[str(slide_demos)], out=str(tmp_path / "run"), steps=4, save_every=4, **TINY_TRAIN),
          say=lambda *_: None)
    report = swap_report(str(tmp_path / "run"), [str(slide_demos)], decides_mm=20.0)
    offline = evaluate_offline(str(tmp_path / "run"), [str(slide_demos)], progress=False)["tasks"][TASK]
    assert {r["keyframe"] for r in report["rows"]} == {int(k) for k in offline["keyframes"]}
    starts = {r["keyframe"]: r for r in report["rows"] if r["start"]}
    assert starts.keys() == {int(k) for k in offline["start_keyframes"]}
    for keyframe, row in starts.items():
        assert row["error_mm"] == pytest.approx(offline["start_keyframes"][str(keyframe)]["stage2_mm"]["median"], abs=0.05)
    for row in report["rows"]:
        assert row["task"] == TASK and row["alternatives"] == 3 and row["moved_mm"] >= 0
        assert all(len(others) == 3 for others in row["others_mm"])
        assert (row["chosen"] is None) == (row["deciding"] == 0)

    # rvt2 diagnose phrasings on the same run: each keyframe start under every phrasing of its own variation
    from rvt2cli.diagnose.phrasings import phrasing_report, phrasings
    from rvt2cli.train.samples import load_samples

    task = get_task(TASK)
    variation, words = phrasings(TASK, task.instruction(0, 2)[0])
    assert variation == 2 and [t for t, _, _ in words] == list(task.instructions) + list(task.paraphrases)
    assert all(text == t.format(**task.variation_values(2)) and held == (t in task.paraphrases) for t, text, held in words)
    assert phrasings(TASK, "a phrasing the task does not have") == (-1, [])
    rows = phrasing_report(str(tmp_path / "run"), [str(slide_demos)])["rows"]
    starts = load_samples(episode_paths([str(slide_demos)]), progress=False, keyframe_starts_only=True)
    for v in range(4):
        mine = [i for i in range(len(starts)) if starts.instructions[starts.instruction_index[i]] in
                [t.format(**task.variation_values(v)) for t in task.instructions]]
        for template, _, held_out in phrasings(TASK, task.instruction(0, v)[0])[1]:
            its = [r for r in rows if r["variation"] == v and r["phrasing"] == template]
            assert sum(r["samples"] for r in its) == len(mine) and all(r["held_out"] == held_out for r in its)
            assert all(r["error_mm"] >= 0 and 0 <= r["far"] <= r["samples"] for r in its)


def test_record_one_variation(tmp_path):
    summary = record(TASK, 2, tmp_path, seed=10, options=RecordOptions(**{**SMALL.__dict__, "variations": "3"}))
    assert summary.successes_per_variation() == {3: 2}
    assert [read_episode(p).variation_index for p in sorted(tmp_path.glob("*.mcap"))] == [3, 3]


def test_an_episode_file_without_a_variation_reads_as_the_only_one(tmp_path):
    """Files of format 1.1 and older store no variation_index."""
    from episode_factory import random_episode

    random_episode(tmp_path / "old.mcap", variation_index=None)
    ep = read_episode(tmp_path / "old.mcap")
    assert "variation_index" not in ep.instruction and ep.variation_index == 0
    random_episode(tmp_path / "new.mcap", variation_index=3)
    assert read_episode(tmp_path / "new.mcap").variation_index == 3


def test_variation_choices_and_the_held_out_split():
    task = _parse("""
name = "t"
env_id = "X"
expert = "m:f"
max_steps = 10
instructions = ["stack {a} on {b}"]
paraphrases = ["put {a} onto {b}"]
held_out_variations = [1]
[[variations]]
a = "red"
b = "blue"
[[variations]]
a = "blue"
b = "red"
[[variations]]
a = "green"
b = "red"
""", "tasks/t.toml")
    assert task.variation_choices() == (0, 1, 2) and task.variation_choices("seen") == (0, 2)
    assert task.variation_choices("held-out") == (1,) and task.variation_choices("2") == (2,)
    assert get_task(TASK).variation_choices("held-out") == ()  # no split: eval --variations held-out skips it
    with pytest.raises(UserError, match="no variation 3"):
        task.variation_choices("3")
    assert [episode_variation(s, (0, 2)) for s in range(10, 14)] == [0, 2, 0, 2]
    assert task.instruction(0, 1) == ("stack blue on red", 0)
    assert task.instruction(0, 1, paraphrase=True) == ("put blue onto red", 0)
    assert task.all_paraphrases() == ["put red onto blue", "put blue onto red", "put green onto red"]
    with pytest.raises(UserError, match="held_out_variations"):
        _parse('name = "t"\nenv_id = "X"\nexpert = "m:f"\nmax_steps = 10\ninstructions = ["x"]\n'
               'held_out_variations = [0]', "tasks/t.toml")


def test_an_instructions_phrasings_are_its_variations_trained_ones():
    drawer = get_task("open_drawer")
    assert drawer.phrasings("open top drawer") == ["open top drawer", "grip the top handle and pull the top drawer open",
                                                   "slide the top drawer open"]
    assert drawer.phrasings("pull out the top drawer") == ["pull out the top drawer"]   # a paraphrase: never trained
    assert drawer.phrasings("open it") == ["open it"]
    assert drawer.variation_of("slide the top drawer open") == 2 and drawer.variation_of("open it") is None



def test_an_episodes_words_are_drawn_by_seed_or_the_first_phrasing_as_the_paper_evaluates():
    """RLBench's tasks return their variation's descriptions and PerAct, RVT and RVT-2 train and evaluate with the
    first (descriptions[0]); rvt2 draws one of the trained phrasings by seed unless --first-phrasing."""
    cups = get_task("stack_cups")
    assert cups.first_phrasing(0) == "stack the other cups on top of the red cup"   # RLBench's first, variation 0
    drawn, first = EvalOptions(checkpoint=None), EvalOptions(checkpoint=None, first_phrasing=True)
    words = {seed: drawn.instruction_for(cups, seed, 3) for seed in range(10_000, 10_100)}
    assert all(text == cups.instruction(seed, 3)[0] for seed, text in words.items())
    assert set(words.values()) == set(cups.phrasings(cups.first_phrasing(3)))      # every trained phrasing turns up
    assert {first.instruction_for(cups, seed, 3) for seed in range(10_000, 10_100)} == {cups.first_phrasing(3)}
    assert first.plan(None)["first_phrasing"] is True and "first_phrasing" not in drawn.plan(None)  # older journals resume
    assert EvalOptions(checkpoint=None, instruction="stack them").instruction_for(cups, 10_000, 3) == "stack them"
    assert EvalOptions(checkpoint=None, paraphrases=True).instruction_for(cups, 10_000, 3) in cups.all_paraphrases()


def test_an_evaluation_plans_the_tasks_in_turns_with_their_variations_drawn_evenly():
    """A stopped evaluation has as many episodes of every task: the jobs go task after task, seed by seed."""
    tasks = ("close_jar", "push_buttons", "insert_peg")   # 20, 50 and 1 variations
    jobs = plan_jobs(EvalOptions(checkpoint=None, oracle=True, tasks=tasks, episodes=3, seed=10000), [], {})
    assert [(job.task, job.seed) for job in jobs] == [(task, seed) for seed in range(10000, 10003) for task in tasks]
    for task in tasks:
        choices = get_task(task).variation_choices()
        assert [job.variation for job in jobs if job.task == task] == [episode_variation(s, choices)
                                                                        for s in range(10000, 10003)]

def test_task_sets():
    assert TASK in tasks_of_set("rlbench18")
    assert {"insert_peg", "push_cube", "stack_pyramid"} <= set(tasks_of_set("maniskill9"))
    assert len(task_sets()["maniskill9"]) == 9
    with pytest.raises(UserError, match="unknown task set 'nope'"):
        tasks_of_set("nope")


def test_cli_lists_variations_and_refuses_unknown_sets_and_variations(cli, tmp_path):
    r = cli("record", "--list-tasks")
    assert r.returncode == 0
    line = next(line for line in r.stdout.splitlines() if line.startswith(TASK))
    assert "4 variations" in line and "rlbench18" in line
    assert_one_line_error(cli("record", "--task-set", "nope", "--out", tmp_path), "unknown task set 'nope'")
    assert_one_line_error(cli("record", "--task", TASK, "--variation", "4", "--out", tmp_path), "no variation 4")
    assert_one_line_error(cli("eval", "--oracle", "--task-set", "nope", "--out", tmp_path), "unknown task set")
    assert_one_line_error(cli("eval", "--oracle", "--tasks", TASK, "--variations", "9", "--out", tmp_path), "no variation 9")
    assert_one_line_error(cli("eval", "--oracle", "--tasks", TASK, "--variations", "held-out", "--out", tmp_path),
                          "has held_out_variations")


def test_oracle_eval_reports_per_variation_with_paraphrases(tmp_path):
    task = get_task(TASK)
    result = evaluate(EvalOptions(checkpoint=None, tasks=(TASK,), episodes=4, seed=10_000, oracle=True, paraphrases=True,
                                  out=str(tmp_path)))
    episodes = result.report["episodes"]
    assert sorted(e["variation"] for e in episodes) == [0, 1, 2, 3]
    for e in episodes:
        assert e["instruction"] == task.instruction(e["seed"], e["variation"], paraphrase=True)[0]
        assert e["instruction"] in task.all_paraphrases()
    per = result.report["tasks"][TASK]["oracle"]["variations"]
    assert set(per) == {"0", "1", "2", "3"} and all(v["episodes"] == 1 for v in per.values())
    assert sum(v["successes"] for v in per.values()) == result.report["tasks"][TASK]["oracle"]["successes"]
    # per phrasing: each episode under the held-out template that made its instruction
    phrasings = result.report["tasks"][TASK]["oracle"]["phrasings"]
    assert set(phrasings) <= set(task.paraphrases) and all(v["held_out"] for v in phrasings.values())
    for template, entry in phrasings.items():
        made = [e for e in episodes if e["instruction"] == template.format(**task.variation_values(e["variation"]))]
        assert entry["episodes"] == len(made) and entry["successes"] == sum(e["success"] for e in made)
    markdown = (tmp_path / "eval.md").read_text()
    assert "Success per variation" in markdown and "color=yellow" in markdown and "held-out paraphrases" in markdown
    assert len(phrasings) > 1 and "Success per phrasing" in markdown and f"{next(iter(phrasings))} (held out)" in markdown


class OtherVariationsKeyframes(KeyframeSource):
    """The expert's keyframes of another variation than the episode's: a policy that ignored the instruction."""

    def __init__(self, env, variation):
        self.env, self.variation = env, variation

    def reset(self, task, seed, instruction):
        self.queue = expert_keyframes(self.env, task, seed, variation=self.variation)[1]

    def next(self, cloud, gripper_open, finger_positions, keyframes_done, retry=0):
        return self.queue[keyframes_done] if keyframes_done < len(self.queue) else None


def test_a_push_onto_another_variations_target_fails_as_wrong_target(slide_env):
    from rvt2cli.eval.report import episode_record

    task = get_task(TASK)
    outcome = run_episode(slide_env, task, 10_001, OtherVariationsKeyframes(slide_env, 0), "slide the block to blue target",
                          variation=1)
    assert not outcome.success and outcome.variation == 1 and outcome.wrong == "wrong_target"
    record = episode_record("policy", outcome)
    assert failure_reason(record, insertion=False) == "wrong_target"
    assert record["final_check"] == {"success": False, "wrong_target": True}  # the task's check at the end, in JSON


def test_record_cli_records_one_variation(cli, tmp_path):
    r = cli("record", "--task", TASK, "--variation", "2", "--episodes", "1", "--seed", "3", "--out", tmp_path,
            "--cameras", "front", "--image-size", "32", "--obs-every", "50", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "episodes per variation: 2: 1" in r.stdout
    assert read_episode(tmp_path / f"{TASK}_0003.mcap").variation_index == 2
    assert_one_line_error(cli("record", "--task", TASK, "--variation", "1", "--hold-out-variations", "--out", tmp_path),
                          "not both")
    assert_one_line_error(cli("eval", "--oracle", "--tasks", TASK, "--paraphrases", "--instruction", "x", "--out", tmp_path),
                          "one of --paraphrases, --first-phrasing and --instruction", "--paraphrases and --instruction were given")
    assert_one_line_error(cli("eval", "--oracle", "--tasks", TASK, "--first-phrasing", "--paraphrases", "--out", tmp_path),
                          "--paraphrases and --first-phrasing were given")
