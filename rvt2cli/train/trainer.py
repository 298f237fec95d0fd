"""`rvt2 train`: the training loop with the paper's system improvements.

bf16 autocast on CUDA, LAMB (8-bit from bitsandbytes when installed), warmup + cosine schedule,
gradient clipping, a guard that skips steps with a non-finite loss or gradient (and stops after too
many), checkpoints that resume exactly, CSV + TensorBoard logs, validation on held-out episodes, and
DDP when started by torchrun.
"""

import csv
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from rvt2cli.data.paths import episode_paths
from rvt2cli.errors import UserError
from rvt2cli.model.config import ModelConfig, get_config
from rvt2cli.model.language import InstructionCache
from rvt2cli.model.loss import policy_loss
from rvt2cli.model.policy import RVT2Policy
from rvt2cli.train.batches import TaskUniformSampler, make_batch, pack
from rvt2cli.train.checkpoint import load_checkpoint, save_checkpoint
from rvt2cli.train.metrics import prediction_errors
from rvt2cli.train.optim import make_optimizer, warmup_cosine
from rvt2cli.train.sample_cache import is_sample_cache, load_sample_cache
from rvt2cli.train.samples import SampleSet, load_samples, select_samples


@dataclass
class TrainOptions:
    data: list[str]
    out: str
    config: str = "rvt2"
    steps: int = 10_000
    batch_size: int = 24
    lr: float | None = None          # default: 1.25e-5 x total batch (the paper's rule)
    weight_decay: float = 1e-4
    warmup: int = 2000               # capped at a tenth of the steps
    clip: float = 5.0
    max_points: int = 50_000
    augment: bool = True             # the paper's translation and yaw augmentation
    seed: int = 0
    device: str = "auto"
    resume: bool = False
    save_every: int = 1000
    val_every: int = 500
    val_episodes: int = 1            # held out per task (tasks with at least 3 episodes)
    log_every: int = 10
    max_bad_steps: int = 50
    include_failures: bool = False
    episodes_per_task: int | None = None   # only each task's first N episodes (the few-demo setting)
    keyframe_starts_only: bool = False     # only samples observed at frame 0 or at a keyframe
    amp: bool = True
    compile: bool = False            # torch.compile the network (H100 training step: 381 -> 560 samples/s)
    eight_bit: bool = True
    render_backend: str = "warp"
    progress: bool = True


@dataclass
class TrainResult:
    run_dir: Path
    steps: int
    losses: list[float] = field(default_factory=list)   # total loss of every step run in this call
    skipped_steps: int = 0
    last_validation: dict | None = None
    seconds: float = 0.0
    packed: object = field(default=None, repr=False)  # the packed training samples (for inspection)


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"--device {name}: no CUDA GPU is available here (torch {torch.__version__}); use --device cpu")
    return torch.device(name)


def load_training_data(data: list[str], include_failures: bool, progress: bool,
                       keyframe_starts_only: bool = False) -> tuple[SampleSet, dict[str, torch.Tensor]]:
    """Samples from one sample cache (with its instruction embeddings) or from episode files (embeddings
    still to compute; with `keyframe_starts_only`, the other samples' clouds are not even fused)."""
    caches = [d for d in data if is_sample_cache(d)]
    if caches:
        if len(data) > 1:
            raise UserError(f"--data: give one sample cache ({caches[0]}) or episode files/folders, not both")
        return load_sample_cache(caches[0])
    return load_samples(episode_paths(data), include_failures, progress=progress, keyframe_starts_only=keyframe_starts_only), {}


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


def count_flops(policy: RVT2Policy, packed, device) -> float | None:
    """Forward FLOPs of one sample (matrix products, convolutions, attention) from torch's counter."""
    from torch.utils.flop_counter import FlopCounterMode

    batch = make_batch(packed, np.array([0]), policy.cfg, torch.Generator().manual_seed(0))
    counter = FlopCounterMode(display=False)
    with counter, torch.no_grad():
        policy(batch.obs, batch.position, batch.rot_bins, batch.stage2_center)
    return float(counter.get_total_flops())


class RunLog:
    """train.csv (one row per logged step) and TensorBoard, written by rank 0 only."""

    FIELDS = ["step", "loss", "heatmap1", "heatmap2", "rot_x", "rot_y", "rot_z", "gripper", "collision",
              "lr", "grad_norm", "samples_per_s", "skipped"]

    def __init__(self, run_dir: Path, resume_step: int):
        self.path = run_dir / "train.csv"
        rows = []
        if resume_step and self.path.exists():  # drop rows written after the checkpoint we resume from
            with open(self.path) as f:
                rows = [r for r in csv.DictReader(f) if int(r["step"]) <= resume_step]
        with open(self.path, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.FIELDS)
            writer.writeheader()
            writer.writerows(rows)
        from torch.utils.tensorboard import SummaryWriter

        self.tb = SummaryWriter(str(run_dir / "tb"), purge_step=resume_step + 1 if resume_step else None)

    def log(self, row: dict) -> None:
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.FIELDS, extrasaction="ignore").writerow(row)
        for key, value in row.items():
            if key != "step" and value is not None and value != "":
                self.tb.add_scalar(f"train/{key}", value, row["step"])

    def log_validation(self, step: int, metrics: dict) -> None:
        for key, value in metrics.items():
            self.tb.add_scalar(f"val/{key}", value, step)
        self.tb.flush()

    def close(self) -> None:
        self.tb.close()


def _distributed() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not torch.distributed.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        torch.distributed.init_process_group(backend)
    return (torch.distributed.get_rank() if world > 1 else 0), world


def train(opts: TrainOptions, say=print) -> TrainResult:
    start_time = time.perf_counter()
    rank, world = _distributed()
    device = pick_device(opts.device)
    if world > 1 and device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    torch.manual_seed(opts.seed)
    cfg: ModelConfig = get_config(opts.config)
    run_dir = Path(opts.out)
    total_batch = opts.batch_size * world
    lr = opts.lr if opts.lr is not None else 1.25e-5 * total_batch
    warmup = max(1, min(opts.warmup, opts.steps // 10))

    resume_ckpt = None
    if opts.resume:
        resume_ckpt = load_checkpoint(run_dir)
        if resume_ckpt.config != cfg:
            raise UserError(f"{run_dir}: was trained with config '{resume_ckpt.config.name}' "
                            f"({resume_ckpt.config.to_dict() if resume_ckpt.config.name == cfg.name else 'another config'}); "
                            f"resume with --config {resume_ckpt.config.name} or train into a new --out")
    elif (run_dir / "last").exists():
        raise UserError(f"{run_dir}: already holds a run; pass --resume to continue it or choose another --out")

    samples, known = load_training_data(opts.data, opts.include_failures, progress=opts.progress and rank == 0,
                                        keyframe_starts_only=opts.keyframe_starts_only)
    selected = select_samples(samples, opts.episodes_per_task, opts.keyframe_starts_only)
    train_idx, val_idx = split_episodes(samples, opts.val_episodes, selected)
    if not train_idx:
        raise UserError(f"--data: no training samples left after holding out {opts.val_episodes} episode(s) per task; "
                        f"lower --val-episodes")
    known = {text: emb[: cfg.lang_tokens] for text, emb in known.items()}  # a cache stores the longest prefix any config uses
    if resume_ckpt:
        known = {**known, **resume_ckpt.instruction_embeddings}
    cache = InstructionCache(cfg.lang_tokens, known)
    lang = cache(samples.instructions)
    packed = pack(samples, train_idx, lang, opts.max_points, device, seed=opts.seed)
    packed_val = pack(samples, val_idx, lang, opts.max_points, device, seed=opts.seed) if val_idx else None
    if rank == 0:
        used_episodes = len({samples.episode_index[i] for i in selected})
        say(f"data: {len(selected)} samples from {used_episodes} episodes of {len(samples.tasks)} task(s) "
            f"({', '.join(samples.tasks)}); {len(train_idx)} train, {len(val_idx)} validation"
            + (f"; skipped {samples.skipped_empty} empty clouds" if samples.skipped_empty else "")
            + (f", {samples.skipped_failures} failed episodes" if samples.skipped_failures else ""))

    torch.manual_seed(opts.seed)  # here: loading the text encoder above may or may not have drawn random numbers
    policy = RVT2Policy(cfg, render_backend=opts.render_backend).to(device)
    if resume_ckpt:
        policy.load_state_dict(resume_ckpt.weights)
    if opts.compile:
        policy.compile_network()
    optimizer, optimizer_name = make_optimizer(policy.parameters(), lr, opts.weight_decay, device, opts.eight_bit)
    schedule = warmup_cosine(optimizer, warmup, opts.steps)
    generator = torch.Generator().manual_seed(opts.seed * 1000 + rank)
    step, skipped = 0, 0
    if resume_ckpt:
        state = resume_ckpt.state()
        optimizer.load_state_dict(state["optimizer"])
        schedule.load_state_dict(state["schedule"])
        generator.set_state(state["generator"][rank] if rank < len(state["generator"]) else state["generator"][0])
        torch.set_rng_state(state["torch_rng"])
        step, skipped = state["step"], state["skipped"]
    if rank == 0:
        params = sum(p.numel() for p in policy.parameters())
        flops = count_flops(policy, packed, device)
        say(f"model: {cfg.name}, {params / 1e6:.1f} M parameters, {flops / 1e9:.1f} GFLOPs forward per sample "
            f"(~{3 * flops / 1e9:.0f} GFLOPs per training sample); optimizer {optimizer_name}, lr {lr:.2e}, "
            f"warmup {warmup}, batch {opts.batch_size} x {world} on {device}" + (", bf16" if opts.amp and device.type == "cuda" else ""))

    model = policy
    if world > 1:
        model = torch.nn.parallel.DistributedDataParallel(policy, device_ids=[device.index] if device.type == "cuda" else None)
    sampler = TaskUniformSampler(packed.task)
    run_dir.mkdir(parents=True, exist_ok=True)
    log = RunLog(run_dir, step) if rank == 0 else None
    if rank == 0 and not opts.resume:
        used = sorted({samples.episodes[samples.episode_index[i]] for i in selected})
        (run_dir / "run.json").write_text(json.dumps({"options": asdict(opts), "episodes": used}, indent=2))
    info = {"tasks": samples.tasks, "bounds": samples.bounds, "rigs": samples.rigs}
    result = TrainResult(run_dir=run_dir, steps=step, skipped_steps=skipped)
    amp = opts.amp and device.type == "cuda"
    bar = tqdm(total=opts.steps, initial=step, desc=f"train {cfg.name}", unit="step", disable=not (opts.progress and rank == 0),
               dynamic_ncols=True)
    rate, last_time = None, time.perf_counter()

    def checkpoint(at_step: int) -> None:
        state = {"optimizer": optimizer.state_dict(), "schedule": schedule.state_dict(), "generator": [generator.get_state()],
                 "torch_rng": torch.get_rng_state(), "step": at_step, "skipped": skipped}
        save_checkpoint(run_dir, at_step, policy, cfg, info, cache.as_dict(), state)

    policy.train()
    try:
        while step < opts.steps:
            batch = make_batch(packed, sampler.sample(opts.batch_size, generator), cfg, generator,
                               max_translation=0.125 if opts.augment else 0.0, max_yaw_deg=45.0 if opts.augment else 0.0)
            with torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=amp):
                outputs = model(batch.obs, batch.position, batch.rot_bins, batch.stage2_center)
            losses = policy_loss(outputs, batch.position, batch.rot_bins, batch.gripper, batch.collision,
                                 cfg.image_size, cfg.heatmap_sigma)
            loss = losses["total"]
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(policy.parameters(), opts.clip)
            step += 1
            loss_value = float(loss.detach())
            if not (math.isfinite(loss_value) and torch.isfinite(grad_norm)):
                skipped += 1
                optimizer.zero_grad(set_to_none=True)
                if skipped > opts.max_bad_steps:
                    raise UserError(f"training diverged: {skipped} steps with a non-finite loss or gradient "
                                    f"(last at step {step}); lower --lr or check the data")
            else:
                optimizer.step()
            schedule.step()
            result.losses.append(loss_value)
            now = time.perf_counter()
            current = total_batch / max(now - last_time, 1e-9)
            rate = current if rate is None else 0.9 * rate + 0.1 * current
            last_time = now
            if rank == 0:
                bar.update(1)
                bar.set_postfix(loss=f"{loss_value:.3f}", lr=f"{schedule.get_last_lr()[0]:.1e}", samples_s=f"{rate:.1f}")
                if step % opts.log_every == 0 or step == opts.steps:
                    log.log({"step": step, "loss": loss_value, **{k: float(v.detach()) for k, v in losses.items() if k != "total"},
                             "lr": schedule.get_last_lr()[0], "grad_norm": float(grad_norm), "samples_per_s": rate,
                             "skipped": skipped})
                if packed_val is not None and (step % opts.val_every == 0 or step == opts.steps):
                    result.last_validation = prediction_errors(policy, packed_val, autocast=amp)
                    log.log_validation(step, result.last_validation)
                    v = result.last_validation
                    bar.write(f"step {step}: validation translation {v['translation_mm']:.1f} mm, rotation {v['rotation_deg']:.1f} deg, "
                              f"gripper {v['gripper_accuracy']:.0%} ({v['samples']} samples)")
                if step % opts.save_every == 0 or step == opts.steps:
                    checkpoint(step)
    finally:
        bar.close()
        if log:
            log.close()
    result.steps, result.skipped_steps = step, skipped
    result.seconds = time.perf_counter() - start_time
    result.packed = packed
    return result
