"""`rvt2 train`: the training loop with the paper's system improvements.

bf16 autocast on CUDA, LAMB (8-bit states on CUDA), warmup + cosine schedule, gradient clipping, a
guard that skips steps with a non-finite loss or gradient on the device (and stops after too many),
checkpoints that resume exactly (every rank's sampling state included), CSV + TensorBoard logs,
offline precision on held-out episodes, and DDP when started by torchrun.

The pieces, in the order a run uses them: `rvt2cli.train.run_folder` (a fresh folder, or a resumed run's
stored options), `rvt2cli.train.training_data` and `data_sharing` (samples -> packed tensors, one copy per
process), `rvt2cli.train.training_setup` (model, optimiser, schedule, `TrainingState`: everything a
checkpoint saves), `TrainStep` (rvt2cli.train.step), and `train` here, the loop that ties them together.
"""

import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tqdm import tqdm

from rvt2cli.errors import UserError
from rvt2cli.train.checkpoint import save_checkpoint
from rvt2cli.train.metrics import headline, precision_report, score_predictions
from rvt2cli.train.options import TrainOptions
from rvt2cli.train.run_folder import RunLog, write_run_json
from rvt2cli.train.step import StepResult
from rvt2cli.train.training_data import TrainingData
from rvt2cli.train.training_setup import setup_training

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
    setup_seconds: float = 0.0           # of `seconds`, before the first step: reading and packing the data, building the model
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


def train(opts: TrainOptions, say=print, data: TrainingData | None = None) -> TrainResult:
    """`data`: the samples, already read (`training_setup.setup_training`); None: read them."""
    start_time = time.perf_counter()
    setup = setup_training(opts, say, data=data)
    opts, rank, world, cfg = setup.opts, setup.rank, setup.world, setup.cfg
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
        write_run_json(run_dir, {"options": opts.to_json(), "episodes": used})
    result = TrainResult(run_dir=run_dir, steps=state.step, skipped_steps=state.skipped,
                         setup_seconds=time.perf_counter() - start_time)
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
        batch = next(batches) if state.step < opts.steps else None
        while state.step < opts.steps:
            lr_now = state.schedule.get_last_lr()[0]
            step_result = train_step(batch)
            state.step += 1
            pending.append((state.step, step_result, lr_now))
            step = state.step
            # the next batch, made while the GPU runs this step (before the read-back below waits for it); a
            # checkpoint of this step keeps the sampling state from before its draws
            sampling_state = state.generator.get_state()
            batch = next(batches) if step < opts.steps else None
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
                    write_run_json(run_dir, {"validation": report})
            if save:
                checkpoint_state = state.save(world, sampling_state)  # every rank takes part (gathers the generators)
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
        write_run_json(run_dir, {"seconds": result.seconds, "setup_seconds": result.setup_seconds,
                                  "samples_per_s": result.samples_per_s, "steps": result.steps, "out_of_time": result.out_of_time})
    return result

