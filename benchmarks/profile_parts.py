"""Where a phase's time goes: the cumulative seconds (and calls) of named functions in a cProfile run.

A part is a list of (file suffix, function name); its time is the sum of their cumulative times, so
parts must not nest inside one another (each is a separate step of the phase)."""

import pstats


def part_seconds(stats: pstats.Stats, parts: dict[str, list[tuple[str, str]]]) -> dict[str, float]:
    return {name: seconds for name, (seconds, _) in part_totals(stats, parts).items()}


def part_totals(stats: pstats.Stats, parts: dict[str, list[tuple[str, str]]]) -> dict[str, tuple[float, int]]:
    """Each part's (cumulative seconds, calls)."""
    found = {name: [0.0, 0] for name in parts}
    for (filename, _, function), (_, calls, _, cumulative, _) in stats.stats.items():
        for name, functions in parts.items():
            if any(filename.endswith(suffix) and function == wanted for suffix, wanted in functions):
                found[name][0] += cumulative
                found[name][1] += calls
    return {name: (seconds, calls) for name, (seconds, calls) in found.items()}
