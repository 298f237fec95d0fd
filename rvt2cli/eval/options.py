"""What `rvt2 eval` runs: its options, kept apart from the simulator so the CLI can show defaults cheaply."""

from dataclasses import dataclass, field

MAX_REPLANS = 3  # re-predictions after an unreachable keyframe, in a row, before an episode gives up
# An episode ends after `keyframe_budget` keyframes (RLBench's 25, the paper's measure) or after this many
# times its task's `max_steps` control steps: a safety net for a policy that keeps the arm busy, sized so
# that it does not cut short a policy that needs the keyframes (the executor servos up to 60 steps at
# each; a task's max_steps is about 2.5x its expert's episode). The report also counts the successes
# within the task's own max_steps.
STEP_BUDGET_SCALE = 2.0


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
    paraphrases: bool = False         # each task's held-out paraphrases instead of its training instructions
    first_phrasing: bool = False      # each variation's first trained phrasing (the paper's evaluation) instead of one drawn by seed
    variations: str = "all"           # which variations the episodes spread over: all, seen, held-out or one index
    video: bool = False
    save_rollouts: bool = False
    keyframe_budget: int = 25
    max_replans: int = MAX_REPLANS    # re-predictions after an unreachable keyframe, in a row
    step_budget_scale: float = STEP_BUDGET_SCALE  # control steps per episode: this x the task's max_steps
    out: str | None = None
    device: str = "cpu"
    resume: bool = False              # continue the evaluation in `out` (its journal) instead of refusing it
    replay: str | None = None         # a recorded evaluation's journal: its policy keyframes instead of a checkpoint's
    insertion_search: bool = True     # search for the hole where an insertion stops at a face (rvt2cli.eval.search)
    stage2_min_points: int | None = None  # overrides the checkpoint's (ModelConfig.stage2_min_points)
    policy_url: str | None = None     # a policy served by `rvt2 serve` instead of a checkpoint loaded here
    token: str | None = field(default=None, repr=False)  # the served policy's shared secret (never in a journal)
    shared_policy: bool = False       # one copy of the checkpoint in the main process answers every worker
    cuda_graph: bool = False          # each worker's policy step replayed as one CUDA graph (the same keyframes)

    @property
    def policy(self) -> str | None:
        """Where the policy's keyframes come from: the checkpoint, or the served policy's URL."""
        return self.checkpoint or self.policy_url

    def plan(self, checkpoint_path: str | None) -> dict:
        """The options that decide which episodes run and how: a resumed evaluation must keep them."""
        plan = {"checkpoint": checkpoint_path, "tasks": list(self.tasks), "episodes": self.episodes, "seed": self.seed,
                "oracle": self.oracle, "demos": list(self.demos), "instruction": self.instruction,
                "keyframe_budget": self.keyframe_budget, "max_replans": self.max_replans,
                "step_budget_scale": self.step_budget_scale, "replay": self.replay,
                "insertion_search": self.insertion_search}
        # options added later join the plan only when set, so that an older rvt2's journal still resumes
        if self.paraphrases:
            plan["paraphrases"] = True
        if self.first_phrasing:
            plan["first_phrasing"] = True
        if self.variations != "all":
            plan["variations"] = self.variations
        if self.stage2_min_points is not None:
            plan["stage2_min_points"] = self.stage2_min_points
        return plan

    def instruction_for(self, task, seed: int, variation: int) -> str:
        """The words an episode is given: --instruction's, or its variation's first trained phrasing
        (--first-phrasing), or one of its trained phrasings (or held-out paraphrases) drawn by its seed."""
        if self.instruction:
            return self.instruction
        if self.first_phrasing:
            return task.first_phrasing(variation)
        return task.instruction(seed, variation, self.paraphrases)[0]
