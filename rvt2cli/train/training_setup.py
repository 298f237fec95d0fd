"""What `rvt2 train` builds before its loop (`setup_training`): the processes and the device, the run's
options and model config, the data, the policy (compiled, under DDP on several GPUs), the optimiser and
schedule, the state a checkpoint keeps, the training step and the stream of batches.
"""

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch._dynamo

from rvt2cli.atomic import check_folder_can_be_made, ensure_folder
from rvt2cli.errors import UserError
from rvt2cli.model.config import ModelConfig
from rvt2cli.model.policy import RVT2Policy
from rvt2cli.runtime import torch_device
from rvt2cli.train.batches import BatchStream, make_batch
from rvt2cli.train.checkpoint import Checkpoint, load_weights
from rvt2cli.train.data_sharing import load_data
from rvt2cli.train.optim import make_optimizer, warmup_cosine
from rvt2cli.train.options import TrainOptions
from rvt2cli.train.run_folder import model_config, resolve_options
from rvt2cli.train.step import TrainStep
from rvt2cli.train.training_data import TrainingData
from rvt2cli.train.training_state import TrainingState, init_distributed


def count_flops(policy: RVT2Policy, packed, device) -> float | None:
    """Forward FLOPs of one sample (matrix products, convolutions, attention) from torch's counter."""
    from torch.utils.flop_counter import FlopCounterMode

    batch = make_batch(packed, np.array([0]), policy.cfg, torch.Generator().manual_seed(0))
    counter = FlopCounterMode(display=False)
    # eagerly: under FlopCounterMode torch would skip compiling the network for the rest of the run
    with counter, torch.no_grad(), policy.eager():
        policy(batch.obs, batch.position, batch.rot_bins, batch.stage2_center)
    return float(counter.get_total_flops())


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


def setup_training(opts: TrainOptions, say=print, ddp_graph_split: bool = False, data: TrainingData | None = None
                   ) -> TrainingSetup:
    """`ddp_graph_split`: compile under DDP as torch does by default (see `data_parallel`); only to study it.
    `data`: the samples, already read (a benchmark trains on one read several times); None: read them."""
    rank, world = init_distributed()
    say = say if rank == 0 else (lambda *_: None)
    device = torch_device(opts.device)
    if world > 1 and device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    torch.manual_seed(opts.seed)
    cfg = model_config(opts)
    run_dir = Path(opts.out)
    opts, resume = resolve_options(opts)
    if resume is not None:  # its inference settings too: a run begun before a config's default changed keeps its own
        cfg = resume.config
    if opts.micro_batch is not None and opts.batch_size % opts.micro_batch:
        raise UserError(f"--micro-batch {opts.micro_batch} does not divide --batch-size {opts.batch_size}; "
                        "give a divisor (every part of a batch is the same size, compiled once)")
    total_batch = opts.batch_size * world
    lr = opts.lr if opts.lr is not None else 1.25e-5 * total_batch
    warmup = max(1, min(opts.warmup, opts.steps // 10))
    if rank == 0:
        check_folder_can_be_made(run_dir, "run folder")

    data = data if data is not None else load_data(opts, cfg, device, opts.progress and rank == 0, resume, say)
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
            f"warmup {warmup}, batch {opts.batch_size} x {world} on {device}"
            + (f" ({opts.batch_size // opts.micro_batch} parts of {opts.micro_batch})" if opts.micro_batch else "")
            + (", bf16" if opts.amp and device.type == "cuda" else ""))

    model = policy if world == 1 else data_parallel(policy, device, split_graphs=ddp_graph_split)
    amp = opts.amp and device.type == "cuda"
    train_step = TrainStep(policy, optimizer, state.schedule, amp, opts.clip, model)
    batches = BatchStream(data.packed, cfg, state.generator, opts.batch_size, opts.augment, opts.start_share,
                          data.task_weights, opts.micro_batch)
    return TrainingSetup(opts, resume, rank, world, device, cfg, data, policy, model, state, train_step, batches, amp,
                         total_batch)

