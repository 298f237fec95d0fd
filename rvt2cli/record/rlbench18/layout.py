"""Scattering objects on the table from the episode's seed, apart from each other."""

import numpy as np


def scatter(rng, count: int, low, high, spacing: float, clear_of=(), clearance: float = 0.0,
            max_tries: int = 10_000) -> np.ndarray:
    """`count` xy points drawn uniformly in the box `low`..`high` (m), each at least `spacing` from the
    others and `clearance` from the points `clear_of`. Rejection sampling: the sequence of draws depends
    only on `rng`'s state, so one seed gives one layout."""
    low, high = np.asarray(low, float), np.asarray(high, float)
    placed = []
    for _ in range(max_tries):
        candidate = low + rng.uniform(size=2) * (high - low)
        if all(np.linalg.norm(candidate - p) >= spacing for p in placed) and \
                all(np.linalg.norm(candidate - np.asarray(p)) >= clearance for p in clear_of):
            placed.append(candidate)
            if len(placed) == count:
                return np.array(placed)
    raise RuntimeError(f"cannot place {count} points {spacing} m apart in {low}..{high}")
