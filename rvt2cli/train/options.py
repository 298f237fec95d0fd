"""What `rvt2 train` runs: its options, kept apart from torch so the command line builds quickly.

A run's options are stored with it (`run.json` and every checkpoint's `config.json`). `--resume`
continues with the stored options; the options in `RUN_DEFINING` shape the data, the model or the
schedule, and a resumed run may not change them. The others only say how and where it runs.
"""

from dataclasses import asdict, dataclass, fields


@dataclass
class TrainOptions:
    data: list[str]
    out: str
    config: str = "rvt2"
    rotation_bins: int | None = None  # Euler-angle bins per axis; None: the config's (72, 5 degrees, as the paper)
    rotation_sigma: float | None = None  # degrees: Gaussian rotation targets this wide; None: the config's (one bin)
    coarse_action_features: bool = False  # the action head also reads stage 1's features (ModelConfig)
    aim_held: bool = False           # once it holds, aim the task's aim_offset instead of the TCP (tasks/*.toml)
    zoom: float | None = None        # stage 2 covers 1/zoom of the workspace; None: the config's (4, as the paper)
    stage2_min_points: int | None = None  # inference, stored in the checkpoint (ModelConfig); None: the config's (200)
    steps: int = 10_000
    batch_size: int = 24
    micro_batch: int | None = None   # rows per forward/backward pass, gradients accumulated to batch_size; None: all
    lr: float | None = None          # default: 1.25e-5 x total batch (the paper's rule)
    weight_decay: float = 1e-4
    warmup: int = 2000               # capped at a tenth of the steps
    clip: float = 5.0
    max_points: int = 50_000
    augment: bool = True             # the paper's translation and yaw augmentation
    seed: int = 0
    device: str = "auto"
    samples_on: str = "auto"         # where the packed clouds live: host, device, or auto (rvt2cli.train.clouds)
    resume: bool = False
    save_every: int = 1000
    val_every: int = 500
    val_episodes: int = 1            # held out per task (tasks with at least 3 episodes)
    log_every: int = 10              # also how often the loop reads values back from the GPU
    max_bad_steps: int = 50
    include_failures: bool = False
    episodes_per_task: int | None = None   # only each task's first N episodes (the few-demo setting)
    keyframe_starts_only: bool = False     # only samples observed at frame 0 or at a keyframe
    start_share: float = 0.0               # this share of each task's draws are keyframe-start samples (0: uniform)
    task_weights: dict[str, float] | None = None  # task -> weight: its share of the draws is weight / sum (others 1); None: uniform
    task_set: str | None = None      # train on the episodes of this named set's tasks only (e.g. rlbench18)
    phrasings: str = "demo"          # demo: a sample's instruction is its demo's; all: each draw takes one of its
                                     # variation's trained phrasings (tasks/*.toml's instructions); first: its
                                     # variation's first phrasing (samples.trained_instructions)
    cameras: tuple[str, ...] | None = None  # train on these cameras' points only (e.g. front: the single-camera setting)
    amp: bool = True
    compile: bool = False            # torch.compile the network (H100 training step: 381 -> 560 samples/s)
    eight_bit: bool = True
    render_backend: str = "warp"
    progress: bool = True
    time_limit: float | None = None  # minutes from the command's start: save a checkpoint and stop (--resume continues)

    def to_json(self) -> dict:
        d = asdict(self)
        d["cameras"] = list(self.cameras) if self.cameras else None
        return d

    @staticmethod
    def from_json(obj: dict) -> "TrainOptions":
        known = {f.name for f in fields(TrainOptions)}
        d = {k: v for k, v in obj.items() if k in known}
        if d.get("cameras"):
            d["cameras"] = tuple(d["cameras"])
        return TrainOptions(**d)


# Options a resumed run must keep (they decide the data, the model, the optimiser or the schedule).
RUN_DEFINING = ("data", "config", "rotation_bins", "rotation_sigma", "coarse_action_features", "aim_held", "zoom",
                "stage2_min_points", "steps", "batch_size", "lr", "weight_decay", "warmup", "clip", "max_points", "augment",
                "seed", "val_episodes", "max_bad_steps", "include_failures", "episodes_per_task", "keyframe_starts_only",
                "start_share", "task_weights", "task_set", "phrasings",
                "cameras", "amp", "eight_bit")


def conflicts(stored: TrainOptions, given: TrainOptions, names=RUN_DEFINING) -> list[str]:
    """The run-defining options in which `given` differs from the run's `stored` ones."""
    return [name for name in names if getattr(stored, name) != getattr(given, name)]
