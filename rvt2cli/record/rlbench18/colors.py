"""RLBench's 20 named colours (`rlbench/const.py`), in its order: a colour task's variation k names colour k."""

import numpy as np

COLORS = (
    ("red", (1.0, 0.0, 0.0)), ("maroon", (0.5, 0.0, 0.0)), ("lime", (0.0, 1.0, 0.0)), ("green", (0.0, 0.5, 0.0)),
    ("blue", (0.0, 0.0, 1.0)), ("navy", (0.0, 0.0, 0.5)), ("yellow", (1.0, 1.0, 0.0)), ("cyan", (0.0, 1.0, 1.0)),
    ("magenta", (1.0, 0.0, 1.0)), ("silver", (0.75, 0.75, 0.75)), ("gray", (0.5, 0.5, 0.5)),
    ("orange", (1.0, 0.5, 0.0)), ("olive", (0.5, 0.5, 0.0)), ("purple", (0.5, 0.0, 0.5)), ("teal", (0.0, 0.5, 0.5)),
    ("azure", (0.0, 0.5, 1.0)), ("violet", (0.5, 0.0, 1.0)), ("rose", (1.0, 0.0, 0.5)), ("black", (0.0, 0.0, 0.0)),
    ("white", (1.0, 1.0, 1.0)),
)

RLBENCH_COLORS = dict(COLORS)  # name -> rgb
COLOR_NAMES = tuple(RLBENCH_COLORS)


def rgba(colour: int | str) -> list[float]:
    """A colour by its index in RLBench's order or by its name."""
    return [*(RLBENCH_COLORS[colour] if isinstance(colour, str) else COLORS[int(colour)][1]), 1.0]


def colour_rng(env) -> np.random.Generator:
    """Who wears which colour, drawn from the episode's seed and variation, apart from the RNG that lays the
    scene out: the poses (and so the simulator state) are the same in every variation of a seed."""
    seed = 0 if env._episode_seed is None else int(env._episode_seed[0])
    return np.random.default_rng([seed, env.variation])


def distractor_colours(rng: np.random.Generator, target: int, count: int) -> list[int]:
    """`count` different colours other than the target's, as RLBench draws them."""
    others = [i for i in range(len(COLORS)) if i != target]
    return [int(i) for i in rng.choice(others, size=count, replace=False)]


def other_color(rng, target: int) -> int:
    """A colour other than `target`, drawn with one draw from `rng` whatever `target` is (so the draws that
    follow, e.g. the layout's, do not depend on the variation)."""
    pick = int(rng.randint(len(COLORS) - 1))
    return pick + (pick >= target)
