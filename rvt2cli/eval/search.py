"""The insertion search: what the executor does when a held object stops at the face of its hole.

A keyframe policy a few millimetres off puts a peg against the box's face beside a hole with 3 mm of
clearance. Pushed on, the peg jams there, or slides back through the fingers and pivots in them, and the
episode is lost. Robots that insert parts do not rely on landing within the clearance: they feel the
contact and search for the hole, e.g. in a spiral or on a grid. The executor does that for a keyframe that
ignores collisions with the gripper closed before and after it, an insertion (`Executor.execute`):

1. it pushes along the straight line to the keyframe and watches the arm: where the TCP stops following
   its command along the push (it lags by more than CONTACT_LAG_M and moves less than CONTACT_SPEED_SHARE
   of the commanded step), something blocks it, and the push stops there, before the fingers give;
2. if the arm then rests more than BLOCKED_M short of the keyframe, the object is at a face. The executor
   probes the plane across the push on a square grid, nearest first (`InsertionSearch.offsets`): back
   off the task's retract (RETRACT_M unless it gives one), shift to the grid point, push PROBE_M past
   where the face stopped it;
3. a probe that ends ENTERED_M deeper than the face may have found the hole: the executor pushes on to
   the keyframe along that shifted line. If the object then goes INSIDE_M past the face (or reaches the
   keyframe), it is in, and the executor servos there as for any keyframe; if it stops again near the
   face, it had only turned or slid in the fingers, and the search goes on.

It reads nothing but the arm's own joints and the keyframe (no scene state, no success check), as a
robot with joint encoders could. The grid's pitch is the task's `search_pitch_mm`, and a probe's
retract its `search_retract_mm`; tasks without a pitch push straight, as RLBench's and the paper's
executor do (`rvt2 eval --no-insertion-search`: every task). The grid is sized to how far a policy misses,
not to the clearance: its 40 probes must reach that far within the episode's control steps, at about 19
steps a probe with a 4 mm retract (`rvt2 diagnose precision-budget --search-pitch/--search-retract` compares
grids on the oracle; docs/RESULTS.md v12).
"""

from dataclasses import dataclass

import numpy as np

from rvt2cli.tasks import Task

CONTACT_LAG_M = 0.004       # the TCP trails its command along the push by more than this...
CONTACT_SPEED_SHARE = 0.3   # ...and moved less than this share of the commanded step: a contact stops it
BLOCKED_M = 0.01            # resting this much short of the keyframe along the push: stopped at a face
RETRACT_M = 0.004           # each probe backs off this far from the face before it shifts (default)
PROBE_M = 0.006             # ...and pushes this far past it
ENTERED_M = 0.003           # a probe that ends this much deeper than the face may have gone into the hole...
INSIDE_M = 0.015            # ...and has, if the push along its line then takes the object this far past the face
MAX_PROBES = 40             # at most this many probes per keyframe (17-19 control steps each)


@dataclass(frozen=True)
class InsertionSearch:
    """Where to probe: a square grid of `pitch_m` across the push, the keyframe's own line first; each
    probe backs off `retract_m` from the face before it shifts."""

    pitch_m: float
    retract_m: float = RETRACT_M
    max_probes: int = MAX_PROBES

    @staticmethod
    def for_task(task: Task) -> "InsertionSearch | None":
        """The task's search (None: a task without `search_pitch_mm` is pushed straight)."""
        if task.search_pitch_mm <= 0:
            return None
        return InsertionSearch(task.search_pitch_mm / 1000.0, task.search_retract_mm / 1000.0)

    def offsets(self) -> np.ndarray:
        """[max_probes, 2] grid points (m) in the plane across the push: by distance from the keyframe's
        line, then by angle, so the probes spiral outwards ring by ring; the first is the line itself."""
        rings = int(np.ceil(np.sqrt(self.max_probes))) + 1
        steps = np.arange(-rings, rings + 1)
        grid = np.stack(np.meshgrid(steps, steps, indexing="ij"), axis=-1).reshape(-1, 2).astype(float)
        order = np.lexsort((np.arctan2(grid[:, 1], grid[:, 0]), np.round(np.hypot(grid[:, 0], grid[:, 1]), 9)))
        return grid[order][: self.max_probes] * self.pitch_m


def across(direction: np.ndarray) -> np.ndarray:
    """[2, 3]: two unit vectors spanning the plane across a push along `direction` (a unit vector), the
    first horizontal where the push is not vertical."""
    side = np.cross(direction, [0.0, 0.0, 1.0])
    if np.linalg.norm(side) < 1e-6:
        side = np.cross(direction, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    return np.stack([side, np.cross(direction, side)])
