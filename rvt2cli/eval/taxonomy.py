"""Why an episode failed: one reason per failed episode, read from its journal record.

The reasons, in the order they are tested (the first that applies names the failure):
- `error`: the simulator raised.
- `wrong_object`, `wrong_target`: the episode ended with the gripper on, or the goal reached by, what
  another variation asks for (the task's `evaluate()` says so, where it can tell).
- `unreachable_no_ik`, `unreachable_no_path`: the source's keyframes could not be reached, re-prediction
  after re-prediction (`Reach.why`): no arm pose within the executor's slack, or no plan to one.
- `grasp_lost`: an object was held after some keyframe and is no longer held, the gripper still closed.
For insertion tasks (`Task.insertion`), where the point is the last centimetre:
- `no_insertion_attempt`: no keyframe moved a held object with collisions ignored, and none brought it
  near the goal either (`NEAR_GOAL_MM`).
- `collision_flag_contrary`: a held object was brought near the goal, but only by keyframes that avoid
  collisions, where every demo's insertion ignores them (`rvt2cli.keyframes.rule`).
- `insertion_short`: an insertion was attempted and ended `gap_mm` short of success (the record keeps
  the smallest gap any keyframe reached).
For every task:
- `stalled`: the budget ran out while the source kept predicting where the arm already was: its last
  `STALL_REPEATS` keyframes each within `STALL_MM` of the one before, the gripper unchanged (the policy
  saw nothing left to do in a scene that was not done).
- `budget_spent`: the keyframe or control-step budget ran out otherwise.
- `source_stopped`: the source had no keyframe left (the oracle at the end of its demo).
"""

import math

REASONS = ("error", "wrong_object", "wrong_target", "unreachable_no_ik", "unreachable_no_path", "grasp_lost", "no_insertion_attempt",
           "collision_flag_contrary", "insertion_short", "stalled", "budget_spent", "source_stopped")
NEAR_GOAL_MM = 30.0  # a held object this close to success counts as brought to the goal
STALL_REPEATS = 5    # keyframes at the end, each this close to the one before, make a stall
STALL_MM = 10.0


def _reached(record: dict) -> list[dict]:
    return [s for s in record["steps"] if s["reached"]]


def stalled(steps: list[dict]) -> bool:
    """Whether the last STALL_REPEATS keyframes each lie within STALL_MM of the one before, the gripper unchanged."""
    if len(steps) <= STALL_REPEATS:
        return False
    tail = steps[-STALL_REPEATS - 1:]
    return all(math.dist(a["target"][:3], b["target"][:3]) * 1000 <= STALL_MM and a["gripper_open"] == b["gripper_open"]
               for a, b in zip(tail, tail[1:]))


def failure_reason(record: dict, insertion: bool) -> str | None:
    """The reason a recorded episode failed (None if it succeeded)."""
    if record["success"]:
        return None
    if record["failure"] == "error":
        return "error"
    if record.get("wrong"):
        return record["wrong"]
    steps = record["steps"]
    if record["failure"] == "planning_failure":
        unreached = [s for s in steps if not s["reached"]]
        return f"unreachable_{unreached[-1].get('why') or 'no_ik'}" if unreached else "unreachable_no_ik"
    reached = _reached(record)
    ever_held = any(s.get("held") for s in reached)
    if ever_held and reached and not reached[-1].get("held") and not reached[-1]["gripper_open"]:
        return "grasp_lost"
    if insertion:
        holding = [s for s in reached if s.get("held") and not s["gripper_open"]]
        attempts = [s for s in holding if s["ignore_collisions"]]
        near_goal = [s for s in holding if s.get("gap_mm") is not None and s["gap_mm"] <= NEAR_GOAL_MM]
        if not attempts:
            return "collision_flag_contrary" if near_goal else "no_insertion_attempt"
        return "insertion_short"
    if record["failure"] != "budget_exhausted":
        return "source_stopped"
    return "stalled" if stalled(steps) else "budget_spent"


def closest_gap_mm(record: dict) -> float | None:
    """The smallest gap to success a held object reached in this episode (mm), if the task measures one."""
    gaps = [s["gap_mm"] for s in _reached(record) if s.get("held") and s.get("gap_mm") is not None]
    return min(gaps) if gaps else None


def count_reasons(records: list[dict], insertion: bool) -> dict[str, int]:
    reasons = [failure_reason(r, insertion) for r in records]
    return {reason: reasons.count(reason) for reason in REASONS if reason in reasons}
