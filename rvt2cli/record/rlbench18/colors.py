"""RLBench's 20 named colours (rlbench/const.py), in its order: a colour variation's index is its place here."""

COLORS = (
    ("red", (1.0, 0.0, 0.0)), ("maroon", (0.5, 0.0, 0.0)), ("lime", (0.0, 1.0, 0.0)), ("green", (0.0, 0.5, 0.0)),
    ("blue", (0.0, 0.0, 1.0)), ("navy", (0.0, 0.0, 0.5)), ("yellow", (1.0, 1.0, 0.0)), ("cyan", (0.0, 1.0, 1.0)),
    ("magenta", (1.0, 0.0, 1.0)), ("silver", (0.75, 0.75, 0.75)), ("gray", (0.5, 0.5, 0.5)),
    ("orange", (1.0, 0.5, 0.0)), ("olive", (0.5, 0.5, 0.0)), ("purple", (0.5, 0.0, 0.5)), ("teal", (0.0, 0.5, 0.5)),
    ("azure", (0.0, 0.5, 1.0)), ("violet", (0.5, 0.0, 1.0)), ("rose", (1.0, 0.0, 0.5)), ("black", (0.0, 0.0, 0.0)),
    ("white", (1.0, 1.0, 1.0)),
)
COLOR_NAMES = tuple(name for name, _ in COLORS)


def rgba(index: int) -> list[float]:
    return [*COLORS[index][1], 1.0]


def other_color(rng, target: int) -> int:
    """A colour other than `target`, drawn with one draw from `rng` whatever `target` is (so the draws that
    follow, e.g. the layout's, do not depend on the variation)."""
    pick = int(rng.randint(len(COLORS) - 1))
    return pick + (pick >= target)
