"""`rvt2 train`: the training loop with the paper's system improvements.

bf16 autocast on CUDA, LAMB (8-bit states on CUDA), warmup + cosine schedule, gradient clipping, a
guard that skips steps with a non-finite loss or gradient on the device (and stops after too many),
checkpoints that resume exactly (every rank's sampling state included), CSV + TensorBoard logs,
offline precision on held-out episodes, and DDP when started by torchrun.

The pieces, in the order a run uses them: `resolve_options` (a resumed run keeps its stored options),
`load_data` (samples -> packed tensors on the device), `TrainingState` (model, optimiser, schedule,
sampling generator, counters: everything a checkpoint saves), `TrainStep` (rvt2cli.train.step), and
`train`, the loop that ties them together.
"""

import csv
import datetime
import json
import os
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from dataclasses import fields as dataclass_fields
from pathlib import Path

import numpy as np
import torch
import torch._dynamo
from tqdm import tqdm

from rvt2cli.atomic import atomic_open, check_folder_can_be_made, ensure_folder
from rvt2cli.data.paths import episode_paths
from rvt2cli.errors import UserError
from rvt2cli.model.config import ModelConfig, get_config
from rvt2cli.model.language import InstructionCache
from rvt2cli.model.policy import RVT2Policy
from rvt2cli.runtime import usable_cores
from rvt2cli.train.batches import BatchStream, PackedSamples, TaskSampler, make_batch, pack
from rvt2cli.train.checkpoint import Checkpoint, load_checkpoint, load_weights, save_checkpoint
from rvt2cli.train.metrics import headline, precision_report, score_predictions, task_rows
from rvt2cli.train.optim import make_optimizer, warmup_cosine
from rvt2cli.train.options import TrainOptions, conflicts
from rvt2cli.train.sample_cache import is_sample_cache, load_sample_cache
from rvt2cli.train.samples import SampleSet, load_samples, phrasing_table, select_samples, trained_instructions
from rvt2cli.train.step import StepResult, TrainStep
from rvt2cli.tasks import aim_offsets, tasks_of_set

__all__ = ["TrainOptions", "TrainResult", "train"]


@dataclass
class TrainResult:
    run_dir: Path
    steps: int
    losses: list[float] = field(default_factory=list)   # total loss of every step run in this call
    skipped_steps: int = 0
    skipped_terms: Counter = field(default_factory=Counter)  # this process's skipped steps by what was not finite
    last_validation: dict | None = None
    seconds: float = 0.0
    samples_per_s: float | None = None   # the loop's throughput after its first logged interval
    packed: object = field(default=None, repr=False)  # the packed training samples (for inspection)
    out_of_time: bool = False            # stopped at --time-limit before the last step, a checkpoint saved


def out_of_time(started: float, limit_minutes: float | None, world: int, device) -> bool:
    """Whether --time-limit is up. Every process asks at the same steps; under DDP they stop together as soon
    as any one's clock says so (the processes started at slightly different times)."""
    if limit_minutes is None:
        return False
    late = time.perf_counter() - started >= 60.0 * limit_minutes
    if world > 1:
        flag = torch.tensor([float(late)], device=device)
        torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
        late = bool(flag.item())
    return late


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"--device {name}: no CUDA GPU is available here (torch {torch.__version__}); use --device cpu")
    return torch.device(name)


# --- options -----------------------------------------------------------------------------------------

RUN_FILES = {"last", "run.json", "train.csv", "validation.csv", "tb", "checkpoints"}


def _own_files(run_dir: Path) -> list[str]:
    """The names in `run_dir` that `rvt2 train` did not write (its hidden temporary files aside)."""
    return sorted(p.name for p in run_dir.iterdir() if p.name not in RUN_FILES and not
                  (p.name.startswith(".") and ".tmp-" in p.name))


def check_run_folder(run_dir: Path, resume: bool) -> None:
    """A fresh run goes into a new or empty folder, or one of a run stopped before its first checkpoint;
    a resumed run needs a checkpoint. One line otherwise; nothing of the user's is written over."""
    has_checkpoint = (run_dir / "last").exists()
    foreign = _own_files(run_dir) if run_dir.is_dir() and not has_checkpoint else []
    if foreign:
        raise UserError(f"{run_dir}: exists and is not an rvt2 run folder (it holds {foreign[0]}); "
                        "train into a new or empty --out")
    if not resume and has_checkpoint:
        raise UserError(f"{run_dir}: already holds a run; pass --resume to continue it or choose another --out")
    if resume and not has_checkpoint:
        if not run_dir.is_dir():
            raise UserError(f"{run_dir}: no such run folder to resume; start the run without --resume")
        raise UserError(f"{run_dir}: the run has no checkpoint yet (it stopped before its first save); "
                        "start it again without --resume")


def stored_options(run_dir: Path) -> TrainOptions | None:
    """The options a run was started with (from its last checkpoint), or None for a run without them."""
    check_run_folder(run_dir, resume=True)
    options = load_checkpoint(run_dir).training_options
    return TrainOptions.from_json(options) if options else None


def resolve_options(opts: TrainOptions) -> tuple[TrainOptions, Checkpoint | None]:
    """A fresh run needs a fresh folder; a resumed run must keep its run-defining options."""
    run_dir = Path(opts.out)
    check_run_folder(run_dir, opts.resume)
    if not opts.resume:
        return opts, None
    ckpt = load_checkpoint(run_dir)
    stored = stored_options(run_dir)
    if stored is not None:
        changed = conflicts(stored, opts)
        if changed:
            name = changed[0]
            raise UserError(f"--{name.replace('_', '-')} {getattr(opts, name)!r} differs from the run's "
                            f"{getattr(stored, name)!r} in {run_dir}; a resumed run keeps its options: "
                            "leave the flag out, or train into a new --out")
    if ckpt.config.network() != model_config(opts).network():
        raise UserError(f"{run_dir}: was trained with config '{ckpt.config.name}'; resume with --config "
                        f"{ckpt.config.name} or train into a new --out")
    return opts, ckpt


def model_config(opts: TrainOptions) -> ModelConfig:
    """The named config, with the run's own rotation bins and targets, action features, zoom and stage-2
    point minimum where it sets them."""
    cfg = get_config(opts.config)
    if opts.rotation_bins:
        cfg = replace(cfg, rotation_bins=opts.rotation_bins)
    if (opts.coarse_action_features or opts.zoom is not None or opts.stage2_min_points) and cfg.stages == 1:
        raise UserError(f"--config {opts.config} has one stage: --zoom, --coarse-action-features and "
                        "--stage2-min-points need a second stage (--config rvt2 or small)")
    if opts.coarse_action_features:
        cfg = replace(cfg, coarse_action_features=True)
    if opts.zoom is not None:
        cfg = replace(cfg, zoom=opts.zoom)
    if opts.stage2_min_points is not None:
        cfg = replace(cfg, stage2_min_points=opts.stage2_min_points)
    return replace(cfg, rotation_sigma_deg=opts.rotation_sigma) if opts.rotation_sigma is not None else cfg


# --- data --------------------------------------------------------------------------------------------

def load_training_data(data: list[str], include_failures: bool, progress: bool, keyframe_starts_only: bool = False,
                       cameras: tuple[str, ...] | None = None, task_set: str | None = None
                       ) -> tuple[SampleSet, dict[str, torch.Tensor]]:
    """Samples from one sample cache (with its instruction embeddings) or from episode files (embeddings
    still to compute; with `keyframe_starts_only`, the other samples' clouds are not even fused; with
    `task_set`, only the episodes of that set's tasks)."""
    tasks = tasks_of_set(task_set) if task_set else None
    caches = [d for d in data if is_sample_cache(d)]
    if caches:
        if len(data) > 1:
            raise UserError(f"--data: give one sample cache ({caches[0]}) or episode files/folders, not both")
        samples, embeddings = load_sample_cache(caches[0])
        if tasks is not None and not set(samples.tasks) <= set(tasks):
            raise UserError(f"{caches[0]}: holds tasks outside --task-set {task_set} "
                            f"({', '.join(sorted(set(samples.tasks) - set(tasks)))}); pack a cache of the set's episodes")
        if cameras and any(list(cameras) != r["cameras"] for r in samples.rigs.values()):
            raise UserError(f"{caches[0]}: its clouds were fused from other cameras than --cameras {','.join(cameras)}; "
                            f"pack the cache with `rvt2 pack-samples --cameras {','.join(cameras)}`")
        return samples, embeddings
    paths = episode_paths(data)
    # one process reads the episodes, with all the cores (a several-GPU run passes the result on: `load_data`)
    return load_samples(paths, include_failures, progress=progress, keyframe_starts_only=keyframe_starts_only,
                        cameras=cameras, tasks=tasks, workers=usable_cores()), {}


def split_episodes(samples, val_episodes: int, selected: list[int] | None = None) -> tuple[list[int], list[int]]:
    """Hold out the last `val_episodes` episodes of every task that has at least 3 (among the selected samples)."""
    selected = list(range(len(samples))) if selected is None else selected
    episode_task = {}
    for i in selected:
        episode_task[samples.episode_index[i]] = samples.task_index[i]
    held = set()
    for t in set(episode_task.values()):
        episodes = sorted(e for e, et in episode_task.items() if et == t)
        if len(episodes) >= 3 and val_episodes > 0:
            held.update(episodes[-val_episodes:])
    train = [i for i in selected if samples.episode_index[i] not in held]
    val = [i for i in selected if samples.episode_index[i] in held]
    return train, val


@dataclass
class TrainingData:
    samples: SampleSet
    selected: list[int]
    packed: PackedSamples
    packed_val: PackedSamples | None
    instructions: InstructionCache
    aim_offsets: dict[str, list[float]] | None = None   # what the targets aim at (--aim-held), per task
    task_weights: np.ndarray | None = None   # per task index (--task-weights); None: tasks drawn uniformly


def load_data(opts: TrainOptions, cfg: ModelConfig, device, progress: bool, resume: Checkpoint | None, say) -> TrainingData:
    """The samples to train on, packed on `device`. In a several-GPU run the first process reads and packs
    them and sends them to the others, whose copy is the same as reading them would give (packing is
    seeded): four processes reading 1,800 rvt2-18 episodes each took 4.5 of a 4 x H200 run's 15 minutes."""
    if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return read_data(opts, cfg, device, progress, resume, say)
    data, error = None, None
    if torch.distributed.get_rank() == 0:
        try:
            data = read_data(opts, cfg, device, progress, resume, say)
        except UserError as e:  # the others would otherwise wait for data that never comes
            error = str(e)
    return share_data(data, error, device)


def pickled_part(data: TrainingData) -> TrainingData:
    """What `share_data` pickles: `data` without the sample set's clouds, its packed samples without their
    tensors but with each tensor's shape and dtype (the tensors travel apart)."""
    def outline(packed):
        if packed is None:
            return None
        tensors = {f.name: getattr(packed, f.name) for f in dataclass_fields(packed) if torch.is_tensor(getattr(packed, f.name))}
        return replace(packed, **dict.fromkeys(tensors)), {name: (t.shape, t.dtype) for name, t in tensors.items()}

    return replace(data, samples=replace(data.samples, xyz=[], rgb=[]), packed=outline(data.packed),
                   packed_val=outline(data.packed_val))


def share_data(data: TrainingData | None, error: str | None, device) -> TrainingData:
    """Process 0's `data` (or its error) in every process: the small parts pickled, the packed tensors sent
    as they are (NCCL between GPUs). Process 0's sample set keeps its clouds, the others' copy has none
    (only the packed ones are trained on)."""
    dist = torch.distributed
    rank = dist.get_rank()
    header = [None]
    if rank == 0:
        header = [("error", error)] if error is not None else [("data", pickled_part(data))]
    dist.broadcast_object_list(header, src=0, device=device if device.type == "cuda" else None)
    kind, payload = header[0]
    if kind == "error":
        raise UserError(payload)

    def allocate(outlined):
        packed, shapes = outlined
        return replace(packed, **{name: torch.empty(shape, dtype=dtype, device=device) for name, (shape, dtype) in shapes.items()})

    received = data if rank == 0 else replace(payload, packed=allocate(payload.packed),
                                              packed_val=payload.packed_val and allocate(payload.packed_val))
    for packed, outlined in ((received.packed, payload.packed), (received.packed_val, payload.packed_val)):
        for name in outlined[1] if outlined is not None else ():
            dist.broadcast(getattr(packed, name), src=0)
    return received


def read_data(opts: TrainOptions, cfg: ModelConfig, device, progress: bool, resume: Checkpoint | None, say) -> TrainingData:
    """Read, select, split, embed and pack the training samples (`load_data` without the sharing)."""
    samples, known = load_training_data(opts.data, opts.include_failures, progress, opts.keyframe_starts_only, opts.cameras,
                                        opts.task_set)
    selected = select_samples(samples, opts.episodes_per_task, opts.keyframe_starts_only)
    train_idx, val_idx = split_episodes(samples, opts.val_episodes, selected)
    if not train_idx:
        raise UserError(f"--data: no training samples left after holding out {opts.val_episodes} episode(s) per task; "
                        f"lower --val-episodes")
    known = {text: emb[: cfg.lang_tokens] for text, emb in known.items()}  # a cache stores the longest prefix any config uses
    if resume:
        known = {**known, **resume.instruction_embeddings}
    cache = InstructionCache(cfg.lang_tokens, known)
    phrasings = None
    if opts.phrasings == "all":
        texts, table, counts = phrasing_table(samples)
        lang, phrasings = cache(texts), (table, counts)
        say(f"phrasings: {len(texts)} instructions for the {len(samples.instructions)} the demos use "
            f"(--phrasings all: up to {table.shape[1]} per variation)")
    else:
        texts = trained_instructions(samples, opts.phrasings)
        lang = cache(texts)
        if opts.phrasings == "first":
            say(f"phrasings: {len(set(texts))} instructions, each variation's first, for the {len(samples.instructions)} "
                "the demos use (--phrasings first)")
    aims = None
    if opts.aim_held:  # a resumed run keeps the offsets it began with, whatever tasks/*.toml says now
        aims = resume.aim_offsets if resume is not None and resume.aim_offsets is not None else aim_offsets(samples.tasks)
    if aims == {}:
        raise UserError(f"--aim-held: none of the tasks ({', '.join(samples.tasks)}) declares an aim_offset in its "
                        "tasks/*.toml; add one (m, in the TCP frame) or leave the flag out")
    weights = task_weight_array(opts.task_weights, samples.tasks)
    packed = pack(samples, train_idx, lang, opts.max_points, device, seed=opts.seed, aim_offsets=aims, phrasings=phrasings)
    packed_val = pack(samples, val_idx, lang, opts.max_points, device, seed=opts.seed, aim_offsets=aims) if val_idx else None
    used_episodes = len({samples.episode_index[i] for i in selected})
    say(f"data: {len(selected)} samples from {used_episodes} episodes of {len(samples.tasks)} task(s) "
        f"({', '.join(samples.tasks)}); {len(train_idx)} train, {len(val_idx)} validation"
        + (f"; skipped {samples.skipped_empty} empty clouds" if samples.skipped_empty else "")
        + (f", {samples.skipped_failures} failed episodes" if samples.skipped_failures else ""))
    if weights is not None:
        shares = TaskSampler(packed.task, task_weights=weights).shares()
        say("task shares of the draws (--task-weights): "
            + ", ".join(f"{samples.tasks[t]} {share:.0%}" for t, share in zip(np.unique(packed.task), shares)))
    return TrainingData(samples, selected, packed, packed_val, cache, aims, weights)


def task_weight_array(task_weights: dict[str, float] | None, tasks: list[str]) -> np.ndarray | None:
    """`--task-weights` as one weight per task index (tasks it leaves out: 1); None: draw tasks uniformly."""
    if task_weights is None:
        return None
    unknown = sorted(set(task_weights) - set(tasks))
    if unknown:
        raise UserError(f"--task-weights: no {', '.join(unknown)} in --data (its tasks: {', '.join(tasks)}); "
                        "name tasks the data holds")
    return np.array([task_weights.get(task, 1.0) for task in tasks], np.float64)


def count_flops(policy: RVT2Policy, packed, device) -> float | None:
    """Forward FLOPs of one sample (matrix products, convolutions, attention) from torch's counter."""
    from torch.utils.flop_counter import FlopCounterMode

    batch = make_batch(packed, np.array([0]), policy.cfg, torch.Generator().manual_seed(0))
    counter = FlopCounterMode(display=False)
    # eagerly: under FlopCounterMode torch would skip compiling the network for the rest of the run
    with counter, torch.no_grad(), policy.eager():
        policy(batch.obs, batch.position, batch.rot_bins, batch.stage2_center)
    return float(counter.get_total_flops())


# --- the state a checkpoint keeps -------------------------------------------------------------------------

DISTRIBUTED_TIMEOUT = datetime.timedelta(hours=1)


def _distributed() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not torch.distributed.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        # the other processes wait in a collective while the first reads the episodes (`load_data`), which can
        # take longer than torch's 10-minute default on a large dataset
        torch.distributed.init_process_group(backend, timeout=DISTRIBUTED_TIMEOUT)
    return (torch.distributed.get_rank() if world > 1 else 0), world


def _gather(value, world: int) -> list:
    """Every rank's `value` (a CPU tensor or a number), in rank order."""
    if world == 1:
        return [value]
    values = [None] * world
    torch.distributed.all_gather_object(values, value)
    return values


@dataclass
class TrainingState:
    """Everything besides the weights that a resumed run needs to continue exactly. A new piece of
    state is added here, in `save` and `restore`, and nowhere else."""

    optimizer: torch.optim.Optimizer
    schedule: torch.optim.lr_scheduler.LRScheduler
    generator: torch.Generator      # this rank's sampling and augmentation
    step: int = 0
    skipped: int = 0

    def save(self, world: int) -> dict:
        """The state of every rank (call on every rank; the result is complete on all of them)."""
        return {"optimizer": self.optimizer.state_dict(), "schedule": self.schedule.state_dict(),
                "generators": _gather(self.generator.get_state(), world), "torch_rng": _gather(torch.get_rng_state(), world),
                "step": self.step, "skipped": self.skipped, "world_size": world}

    def restore(self, state: dict, rank: int, world: int, where: Path) -> None:
        saved_world = state.get("world_size", len(state["generators"]))
        if saved_world != world:
            raise UserError(f"{where}: the run was trained by {saved_world} process(es), this resume has {world}; "
                            f"resume with the same number (torchrun --nproc-per-node {saved_world})")
        self.optimizer.load_state_dict(state["optimizer"])
        self.schedule.load_state_dict(state["schedule"])
        self.generator.set_state(state["generators"][rank])
        torch.set_rng_state(state["torch_rng"][rank])
        self.step, self.skipped = int(state["step"]), int(state["skipped"])


# --- logs ----------------------------------------------------------------------------------------------

class RunLog:
    """train.csv (one row per logged step), validation.csv (precision per task and keyframe at each
    validation) and TensorBoard, written by rank 0 only."""

    FIELDS = ["step", "loss", "heatmap1", "heatmap2", "rot_x", "rot_y", "rot_z", "gripper", "collision",
              "lr", "grad_norm", "samples_per_s", "skipped"]
    VAL_FIELDS = ["step", "task", "keyframe", "samples", "stage1_mm_median", "stage1_mm_p90", "stage2_mm_median",
                  "stage2_mm_p90", "rotation_deg_median", "rotation_deg_p90", "gripper_accuracy", "collision_accuracy"]

    def __init__(self, run_dir: Path, resume_step: int):
        self.train_csv = run_dir / "train.csv"
        self.val_csv = run_dir / "validation.csv"
        for path, fields in ((self.train_csv, self.FIELDS), (self.val_csv, self.VAL_FIELDS)):
            self._restart(path, fields, resume_step)
        from torch.utils.tensorboard import SummaryWriter

        self.tb = SummaryWriter(str(run_dir / "tb"), purge_step=resume_step + 1 if resume_step else None)

    @staticmethod
    def _restart(path: Path, fields: list[str], resume_step: int) -> None:
        """Keep the rows up to the checkpoint a run resumes from (none for a new run)."""
        rows = []
        if resume_step and path.exists():
            with open(path) as f:
                rows = [r for r in csv.DictReader(f) if int(r["step"]) <= resume_step]
        with atomic_open(path, "w") as f:
            writer = csv.DictWriter(f, fieldnames=fields)
            writer.writeheader()
            writer.writerows(rows)

    def log(self, row: dict) -> None:
        with open(self.train_csv, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.FIELDS, extrasaction="ignore").writerow(row)
        for key, value in row.items():
            if key != "step" and value is not None and value != "":
                self.tb.add_scalar(f"train/{key}", value, row["step"])

    def log_validation(self, step: int, numbers: dict, report: dict) -> None:
        for key, value in numbers.items():
            if value is not None:
                self.tb.add_scalar(f"val/{key}", value, step)
        rows = []
        for task, entry in report["tasks"].items():
            for keyframe, s in task_rows(entry):
                rows.append({"step": step, "task": task, "keyframe": keyframe, "samples": s["samples"],
                             "stage1_mm_median": s["stage1_mm"]["median"], "stage1_mm_p90": s["stage1_mm"]["p90"],
                             "stage2_mm_median": s["stage2_mm"]["median"], "stage2_mm_p90": s["stage2_mm"]["p90"],
                             "rotation_deg_median": s["rotation_deg"]["median"], "rotation_deg_p90": s["rotation_deg"]["p90"],
                             "gripper_accuracy": s["gripper_accuracy"], "collision_accuracy": s["collision_accuracy"]})
        with open(self.val_csv, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.VAL_FIELDS).writerows(rows)
        self.tb.flush()

    def close(self) -> None:
        self.tb.close()


def _write_run_json(run_dir: Path, update: dict) -> None:
    path = run_dir / "run.json"
    content = json.loads(path.read_text()) if path.exists() else {}
    content.update(update)
    with atomic_open(path, "w") as f:
        json.dump(content, f, indent=2)


# --- the loop ------------------------------------------------------------------------------------------

def non_finite_terms(step: StepResult) -> list[str]:
    """What was not finite in a skipped step, as this process saw it: its loss terms, or else only the
    gradient (which, averaged over processes, may come from another process's loss)."""
    terms = [name for name, value in step.losses.items() if name != "total" and not torch.isfinite(value).item()]
    return terms or ["gradient only"]


def describe_terms(counts: Counter) -> str:
    """Counter({"heatmap2": 5, "gradient only": 2}) -> "heatmap2 in 5 steps, gradient only in 2 steps" (most
    first, then by name)."""
    ordered = sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))
    return ", ".join(f"{name} in {n} step{'s' if n != 1 else ''}" for name, n in ordered)


@dataclass
class TrainingSetup:
    """What `train` builds before its loop (and `benchmarks/ddp_nonfinite.py` drives step by step)."""

    opts: TrainOptions
    resume: Checkpoint | None
    rank: int
    world: int
    device: torch.device
    cfg: ModelConfig
    data: TrainingData
    policy: RVT2Policy
    model: torch.nn.Module     # what runs the forward pass: the policy, or its DistributedDataParallel wrapper
    state: TrainingState
    train_step: TrainStep
    batches: BatchStream
    amp: bool
    total_batch: int


def data_parallel(policy: RVT2Policy, device: torch.device, split_graphs: bool = False) -> torch.nn.Module:
    """The policy under DistributedDataParallel, its compiled parts each traced as one graph.

    By default Dynamo cuts every compiled graph under DDP at DDP's gradient buckets (its DDPOptimizer,
    `torch._dynamo.config.optimize_ddp`), so that each bucket's all-reduce can start while the rest of the
    backward runs. With bf16 autocast (torch 2.11, 2 x H200) those cut graphs gave a non-finite heatmap
    loss in about one step in ten, on one rank at a time, and not reproducibly: the same batch with the same
    weights was finite again in half the reruns, and always finite through the uncut compiled graphs or
    eagerly (benchmarks/ddp_nonfinite.py, experiments/ddp_2tasks.toml; docs/BENCHMARKS.md). Uncut graphs
    skipped no step, at the same speed. `split_graphs=True` restores torch's default, to study it."""
    torch._dynamo.config.optimize_ddp = split_graphs
    return torch.nn.parallel.DistributedDataParallel(policy, device_ids=[device.index] if device.type == "cuda" else None)


def setup_training(opts: TrainOptions, say=print, ddp_graph_split: bool = False) -> TrainingSetup:
    """`ddp_graph_split`: compile under DDP as torch does by default (see `data_parallel`); only to study it."""
    rank, world = _distributed()
    say = say if rank == 0 else (lambda *_: None)
    device = pick_device(opts.device)
    if world > 1 and device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    torch.manual_seed(opts.seed)
    cfg = model_config(opts)
    run_dir = Path(opts.out)
    opts, resume = resolve_options(opts)
    if resume is not None:  # its inference settings too: a run begun before a config's default changed keeps its own
        cfg = resume.config
    total_batch = opts.batch_size * world
    lr = opts.lr if opts.lr is not None else 1.25e-5 * total_batch
    warmup = max(1, min(opts.warmup, opts.steps // 10))
    if rank == 0:
        check_folder_can_be_made(run_dir, "run folder")

    data = load_data(opts, cfg, device, opts.progress and rank == 0, resume, say)
    if rank == 0:  # only now: data that cannot be trained on leaves no empty run folder behind
        ensure_folder(run_dir, "run folder")
    torch.manual_seed(opts.seed)  # here: loading the text encoder above may or may not have drawn random numbers
    policy = RVT2Policy(cfg, render_backend=opts.render_backend).to(device)
    if resume:
        load_weights(policy, resume)
    if opts.compile:
        policy.compile_network()
    optimizer, optimizer_name = make_optimizer(policy.parameters(), lr, opts.weight_decay, device, opts.eight_bit)
    state = TrainingState(optimizer, warmup_cosine(optimizer, warmup, opts.steps),
                          torch.Generator().manual_seed(opts.seed * 1000 + rank))
    if resume:
        state.restore(resume.state(), rank, world, resume.path)
    if rank == 0:
        params = sum(p.numel() for p in policy.parameters())
        flops = count_flops(policy, data.packed, device)
        say(f"model: {cfg.name}, {params / 1e6:.1f} M parameters, {flops / 1e9:.1f} GFLOPs forward per sample "
            f"(~{3 * flops / 1e9:.0f} GFLOPs per training sample); optimizer {optimizer_name}, lr {lr:.2e}, "
            f"warmup {warmup}, batch {opts.batch_size} x {world} on {device}" + (", bf16" if opts.amp and device.type == "cuda" else ""))

    model = policy if world == 1 else data_parallel(policy, device, split_graphs=ddp_graph_split)
    amp = opts.amp and device.type == "cuda"
    train_step = TrainStep(policy, optimizer, state.schedule, amp, opts.clip, model)
    batches = BatchStream(data.packed, cfg, state.generator, opts.batch_size, opts.augment, opts.start_share,
                          data.task_weights)
    return TrainingSetup(opts, resume, rank, world, device, cfg, data, policy, model, state, train_step, batches, amp,
                         total_batch)


def train(opts: TrainOptions, say=print) -> TrainResult:
    start_time = time.perf_counter()
    setup = setup_training(opts, say)
    opts, resume, rank, world, cfg = setup.opts, setup.resume, setup.rank, setup.world, setup.cfg
    data, policy, state, train_step, batches = setup.data, setup.policy, setup.state, setup.train_step, setup.batches
    amp, total_batch, run_dir = setup.amp, setup.total_batch, Path(opts.out)
    say = say if rank == 0 else (lambda *_: None)
    samples = data.samples
    info = {"tasks": samples.tasks, "bounds": samples.bounds, "rigs": samples.rigs, "options": opts.to_json()}
    if data.aim_offsets is not None:
        info["aim_offsets"] = data.aim_offsets
    log = RunLog(run_dir, state.step) if rank == 0 else None
    if rank == 0 and not opts.resume:
        used = sorted({samples.episodes[samples.episode_index[i]] for i in data.selected})
        _write_run_json(run_dir, {"options": opts.to_json(), "episodes": used})
    result = TrainResult(run_dir=run_dir, steps=state.step, skipped_steps=state.skipped)
    bar = tqdm(total=opts.steps, initial=state.step, desc=f"train {cfg.name}", unit="step",
               disable=not (opts.progress and rank == 0), dynamic_ncols=True)
    pending: list = []   # (step, StepResult, lr) not yet read back from the device
    first_step = state.step
    last_read, last_read_step = time.perf_counter(), state.step

    def read_back() -> None:
        """Bring the pending steps' numbers to the host (one synchronisation), log them, watch divergence."""
        nonlocal pending, last_read, last_read_step
        if not pending:
            return
        totals = torch.stack([r.losses["total"] for _, r, _ in pending]).float().cpu().tolist()
        finite = torch.stack([r.finite for _, r, _ in pending]).cpu().tolist()
        now = time.perf_counter()
        rate = total_batch * (pending[-1][0] - last_read_step) / max(now - last_read, 1e-9)
        for (at, bad, _), ok in zip(pending, finite):
            if not ok:
                state.skipped += 1
                result.skipped_terms.update(non_finite_terms(bad))
                if state.skipped > opts.max_bad_steps:
                    where = f" on process {rank} of {world}" if world > 1 else ""
                    raise UserError(f"training diverged: {state.skipped} steps with a non-finite loss or gradient "
                                    f"(last at step {at}; not finite{where}: {describe_terms(result.skipped_terms)}); "
                                    f"lower --lr or check the data" + ("; or train on one GPU to compare" if world > 1 else ""))
        result.losses.extend(totals)
        at, last, lr_now = pending[-1]
        if rank == 0:
            if last_read_step > first_step:  # the first interval includes compilation and warm-up
                result.samples_per_s = rate
            log.log({"step": at, "loss": totals[-1], **{k: float(v) for k, v in last.losses.items() if k != "total"},
                     "lr": lr_now, "grad_norm": float(last.grad_norm), "samples_per_s": rate, "skipped": state.skipped})
            bar.update(at - bar.n)
            bar.set_postfix(loss=f"{totals[-1]:.3f}", lr=f"{lr_now:.1e}", samples_s=f"{rate:.1f}")
        pending, last_read, last_read_step = [], now, at

    policy.train()
    try:
        while state.step < opts.steps:
            batch = next(batches)
            lr_now = state.schedule.get_last_lr()[0]
            step_result = train_step(batch)
            state.step += 1
            pending.append((state.step, step_result, lr_now))
            step = state.step
            validate = data.packed_val is not None and (step % opts.val_every == 0 or step == opts.steps)
            save = step % opts.save_every == 0 or step == opts.steps
            if step % opts.log_every == 0 or validate or save or step == opts.steps:
                read_back()
                if step < opts.steps and out_of_time(start_time, opts.time_limit, world, setup.device):
                    result.out_of_time = save = True
            if validate and rank == 0:
                with policy.eager():  # its batches have other sizes than the compiled training step's
                    scores = score_predictions(policy, data.packed_val, autocast=amp)
                report = precision_report(scores, samples.tasks)
                result.last_validation = headline(report["overall"])
                log.log_validation(step, result.last_validation, report)
                v = result.last_validation
                bar.write(f"step {step}: validation stage-2 error {v['translation_mm_median']:.1f} mm median "
                          f"({v['translation_mm_p90']:.1f} p90), rotation {v['rotation_deg_median']:.1f} deg, "
                          f"gripper {v['gripper_accuracy']:.0%} ({v['samples']} samples)")
                if step == opts.steps:
                    _write_run_json(run_dir, {"validation": report})
            if save:
                checkpoint_state = state.save(world)  # every rank takes part (gathers the generators)
                if rank == 0:
                    save_checkpoint(run_dir, step, policy, cfg, info, data.instructions.as_dict(), checkpoint_state)
            if result.out_of_time:
                say(f"--time-limit: {opts.time_limit:g} min reached at step {step} of {opts.steps}; checkpoint saved. "
                    f"Continue with: rvt2 train --out {run_dir} --resume")
                break
    finally:
        bar.close()
        if log:
            log.close()
    result.steps, result.skipped_steps = state.step, state.skipped
    result.seconds = time.perf_counter() - start_time
    result.packed = data.packed
    if rank == 0:
        _write_run_json(run_dir, {"seconds": result.seconds, "samples_per_s": result.samples_per_s, "steps": result.steps,
                                  "out_of_time": result.out_of_time})
    return result

