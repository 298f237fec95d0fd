"""What `rvt2 eval` runs: its options, kept apart from the simulator so the CLI can show defaults cheaply."""

from dataclasses import dataclass


@dataclass(frozen=True)
class EvalOptions:
    checkpoint: str | None
    tasks: tuple[str, ...] = ()       # default: the checkpoint's training tasks
    episodes: int = 25
    seed: int = 10_000                # demos are recorded from seed 0: these seeds are unseen
    workers: int = 1
    oracle: bool = False
    demos: tuple[str, ...] = ()       # oracle from these recorded demos (their seeds) instead of the expert
    instruction: str | None = None    # another phrasing of the instruction
    video: bool = False
    save_rollouts: bool = False
    keyframe_budget: int = 25
    out: str | None = None
    device: str = "cpu"
