"""rvt2-18 tasks insert_onto_square_peg, place_shape_in_shape_sorter, place_wine_at_rack_location and
light_bulb_in, on the real simulator: each starts unsolved, its expert solves a seed, that end state fails
another variation's instruction, and the variation leaves the scene alone."""

import pytest
import torch

from rvt2cli.record.expert import run_expert
from rvt2cli.record.scene import make_env
from rvt2cli.tasks import get_task

# task: (seed, the variation its expert solves, another variation). The variations differ from task to task.
CASES = {
    "insert_onto_square_peg": (10013, 13, 4),
    "place_shape_in_shape_sorter": (10002, 2, 0),
    "place_wine_at_rack_location": (10001, 1, 2),
    "light_bulb_in": (10007, 7, 12),
}


@pytest.fixture(scope="module", params=sorted(CASES))
def task_env(request):
    task = get_task(request.param)
    env = make_env(task)
    yield task, env, CASES[request.param]
    env.close()


def _success(env) -> bool:
    return bool(env.unwrapped.evaluate()["success"][0])


def test_unsolved_at_reset_and_the_variation_leaves_the_scene_alone(task_env):
    task, env, (seed, variation, other) = task_env
    states = []
    for k in (variation, other):
        env.reset(seed=seed, options={"variation": k})
        assert not _success(env)
        states.append(env.unwrapped.get_state_dict())
    assert states[0].keys() == states[1].keys()
    for group in states[0]:
        for name, value in states[0][group].items():
            assert torch.equal(value, states[1][group][name]), f"{task.name}: {group}/{name} differs between variations"


def test_expert_solves_its_variation_and_not_another(task_env):
    task, env, (seed, variation, other) = task_env
    run = run_expert(env, task.expert, seed, max_frames=task.max_steps, variation=variation)
    assert run.status == "success" and _success(env)
    env.unwrapped.variation = other
    assert not _success(env), f"{task.name}: the end state of variation {variation} also solves variation {other}"
