"""rvt2-18 tasks push_buttons, reach_and_drag, sweep_to_dustpan_of_size and turn_tap, on the real simulator:
not solved at reset, solved by their expert, the solution not a success of another variation, and one
initial scene per seed whatever the variation."""

import pytest
import torch

from rvt2cli.record.expert import run_expert
from rvt2cli.record.scene import make_env
from rvt2cli.tasks import get_task

# task -> (seed, the variation its expert solves, another variation its solution must not satisfy, the flag
# that the other variation raises on it, if any)
CASES = {
    "push_buttons": (3, 2, 1, "wrong_object"),  # maroon, green, blue pressed: one too many for "maroon, then green"
    "reach_and_drag": (4, 7, 0, "wrong_target"),  # the cube on the cyan square, not on a red one
    "sweep_to_dustpan_of_size": (6, 1, 0, "wrong_target"),  # the dirt in the short dustpan, not in the tall one
    "turn_tap": (7, 1, 0, "wrong_object"),  # the right handle turned, not the left
}


@pytest.fixture(scope="module", params=sorted(CASES))
def task_env(request):
    task = get_task(request.param)
    env = make_env(task)
    yield task, env
    env.close()


def _success(env) -> bool:
    return bool(env.unwrapped.evaluate()["success"].item())


def test_toml_lists_the_environments_variations(task_env):
    task, env = task_env
    assert task.num_variations == env.unwrapped.num_variations > 1
    assert "rlbench18" in task.task_sets and task.paraphrases
    assert len(set(task.all_instructions())) > len(task.instructions)  # the variations' instructions differ


def test_not_solved_at_reset(task_env):
    task, env = task_env
    for variation in (0, task.num_variations - 1):
        env.reset(seed=11, options={"variation": variation})
        assert not _success(env), (task.name, variation)


def test_expert_solves_and_the_solution_is_not_another_variations(task_env):
    task, env = task_env
    seed, variation, other, flag = CASES[task.name]
    run = run_expert(env, task.expert, seed, max_frames=task.max_steps, variation=variation)
    assert run.status == "success", (task.name, run.status, len(run.frames))
    env.unwrapped.variation = other
    info = env.unwrapped.evaluate()
    assert not bool(info["success"].item()), (task.name, other)
    if flag:
        assert bool(info[flag].item()), (task.name, other, flag)
    env.unwrapped.variation = variation
    assert _success(env)


def test_initial_scene_is_the_same_in_every_variation(task_env):
    task, env = task_env
    states = []
    for variation in (0, task.num_variations - 1):
        env.reset(seed=5, options={"variation": variation})
        states.append(env.unwrapped.get_state_dict())
    first, last = states
    assert first.keys() == last.keys()
    for group in first:
        assert first[group].keys() == last[group].keys()
        for name in first[group]:
            assert torch.equal(first[group][name], last[group][name]), (task.name, group, name)


def test_push_buttons_toml_names_the_colours_the_env_presses():
    from rvt2cli.record.rlbench18.push_buttons import NUM_VARIATIONS, variation_colors

    task = get_task("push_buttons")
    assert task.num_variations == NUM_VARIATIONS == 50
    assert [task.variation_values(v)["order"] for v in range(NUM_VARIATIONS)] == \
           [", ".join(variation_colors(v)) for v in range(NUM_VARIATIONS)]
    assert task.instruction(0, 2)[0] in ("push the maroon button, then push the green button, then push the blue button",
                                         "press the maroon button, then press the green button, then press the blue button",
                                         "push down the button with the maroon base, then the green one, then the blue one")
    assert set(task.held_out_variations) < set(range(NUM_VARIATIONS))
