"""The training loop against its step: where `rvt2 train`'s samples/s go.

    python -m benchmarks.loop_bench --data DEMOS|CACHE [--config rvt2] [--batch-size 192] [--compile]
                                    [--steps 20] [--json out.json] [--profile DIR] [--quick]

First `rvt2 train` itself for 2 x --steps steps (validation off; its rate over the second half),
then the `TrainStep` that it runs, on one policy (compiled once):
  synthetic    one synthetic batch of uniform clouds, reused (what benchmarks/policy_bench.py times)
  real         one batch of the real training samples, reused: what the data itself costs on the GPU
  loop         a fresh batch every step from `BatchStream`, as `rvt2 train` draws them
For each: wall time per step over --steps steps after warm-up (synchronised at both ends only), and the
host's own time per step (how long the calls take to return: where it reaches the wall time, the GPU
waits for the host). Also the host and full time of one batch (`make_batch`), the synchronising CUDA
calls of two loop steps (torch.cuda.set_sync_debug_mode), and with --profile the busiest GPU kernels
and the GPU's busy time per step of `real` and `loop`.
"""

import argparse
import gc
import json
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from benchmarks.machine import describe
from benchmarks.policy_bench import synthetic_train_batch, timer
from rvt2cli.model.config import get_config
from rvt2cli.model.policy import RVT2Policy
from rvt2cli.train.batches import BatchStream
from rvt2cli.train.optim import make_optimizer, warmup_cosine
from rvt2cli.train.step import TrainStep
from rvt2cli.train.data_sharing import load_data
from rvt2cli.train.trainer import TrainOptions, train


def time_steps(step, next_batch, steps: int, warmup: int, device) -> dict:
    """Wall and host milliseconds per step of `step(next_batch())`."""
    for _ in range(warmup):
        step(next_batch())
    start, host = timer(device), 0.0
    for _ in range(steps):
        t = time.perf_counter()
        step(next_batch())
        host += time.perf_counter() - t
    wall = timer(device) - start
    return {"wall_ms": 1000 * wall / steps, "host_ms": 1000 * host / steps}


def synchronising_calls(step, next_batch, steps: int) -> list[str]:
    """Where the loop waits for the GPU: every synchronising CUDA call of `steps` steps (file:line: what)."""
    found = []
    torch.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for _ in range(steps):
                step(next_batch())
    finally:
        torch.cuda.set_sync_debug_mode(0)
    for w in caught:
        if "synchroniz" in str(w.message):
            found.append(f"{Path(w.filename).name}:{w.lineno}: {str(w.message).splitlines()[0][:120]}")
    return found


def profile(step, next_batch, steps: int, folder: Path, name: str) -> dict:
    """The GPU's busy time per step and the busiest kernels (torch.profiler) over `steps` steps."""
    from torch.profiler import ProfilerActivity

    with torch.profiler.profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            step(next_batch())
        torch.cuda.synchronize()
    averages = prof.key_averages()
    sort = "self_device_time_total" if hasattr(averages[0], "self_device_time_total") else "self_cuda_time_total"
    table = averages.table(sort_by=sort, row_limit=30)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"profile_{name}.txt").write_text(table)
    busy_us = 0.0
    for event in prof.events():
        if event.device_type == torch.autograd.DeviceType.CUDA:
            busy_us += event.device_time_total if hasattr(event, "device_time_total") else event.cuda_time_total
    top = sorted(averages, key=lambda e: getattr(e, sort), reverse=True)[:12]
    return {"gpu_busy_ms_per_step": busy_us / 1000 / steps,
            "top_kernels_ms_per_step": {e.key[:80]: getattr(e, sort) / 1000 / steps for e in top}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", help="annotated episodes (files or folders) or one sample cache")
    parser.add_argument("--config", default="rvt2")
    parser.add_argument("--batch-size", type=int, default=192)
    parser.add_argument("--points", type=int, default=50_000)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--render-backend", default="warp")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--profile", help="a folder for torch.profiler tables (CUDA)")
    parser.add_argument("--quick", action="store_true", help="a tiny configuration: checks that it runs (CI)")
    args = parser.parse_args()
    if args.quick:
        args.config, args.batch_size, args.points, args.steps, args.warmup = "small", 2, 2000, 2, 1
    device = torch.device(args.device)
    cfg = get_config(args.config)
    opts = TrainOptions(data=args.data, out=tempfile.mkdtemp(prefix="loop_bench_"), config=args.config,
                        batch_size=args.batch_size, max_points=args.points, val_episodes=0, progress=False,
                        render_backend=args.render_backend, device=str(device))
    # the command's own loop: its rate over the second half (the first includes loading and compiling)
    run = train(replace(opts, out=str(Path(opts.out) / "run"), steps=2 * args.steps, warmup=1, log_every=args.steps,
                        save_every=2 * args.steps, compile=args.compile), say=lambda *_: None)
    rows = {"rvt2 train": {"wall_ms": 1000 * args.batch_size / run.samples_per_s, "host_ms": None,
                           "samples_per_s": run.samples_per_s}}
    print(f"rvt2 train: {run.samples_per_s:.1f} samples/s", flush=True)
    del run
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
    data = load_data(opts, cfg, device, progress=False, resume=None, say=print)
    torch.manual_seed(0)
    policy = RVT2Policy(cfg, render_backend=args.render_backend).to(device)
    if args.compile:
        policy.compile_network()
    lr = 1.25e-5 * args.batch_size
    optimizer, optimizer_name = make_optimizer(policy.parameters(), lr, opts.weight_decay, device, opts.eight_bit)
    amp = device.type == "cuda"
    train_step = TrainStep(policy, optimizer, warmup_cosine(optimizer, 10, 100_000), amp, opts.clip)
    policy.train()

    synthetic = synthetic_train_batch(cfg, args.batch_size, args.points, device)
    real = next(BatchStream(data.packed, cfg, torch.Generator().manual_seed(0), args.batch_size))

    def stream() -> BatchStream:
        return BatchStream(data.packed, cfg, torch.Generator().manual_seed(1), args.batch_size)

    # one batch on its own: the host's part, and all of it (GPU included)
    made = stream()
    next(made)
    host_times, full_times = [], []
    for _ in range(5):
        t0 = timer(device)
        next(made)
        host_times.append(time.perf_counter() - t0)
        full_times.append(timer(device) - t0)
    rows["batch_only"] = {"host_ms": 1000 * float(np.median(host_times)), "wall_ms": 1000 * float(np.median(full_times))}

    variants = {"synthetic": lambda: synthetic, "real": lambda: real, "loop": stream().__next__}
    for name, next_batch in variants.items():
        rows[name] = time_steps(train_step, next_batch, args.steps, args.warmup, device)
        rows[name]["samples_per_s"] = args.batch_size / rows[name]["wall_ms"] * 1000
        print(f"{name}: {rows[name]['wall_ms']:.1f} ms/step wall, {rows[name]['host_ms']:.1f} ms host, "
              f"{rows[name]['samples_per_s']:.1f} samples/s", flush=True)

    result = {"machine": describe(), "device": str(device), "config": cfg.name, "batch": args.batch_size,
              "points": args.points, "compiled": args.compile, "optimizer": optimizer_name, "bf16": amp,
              "samples": len(data.packed), "variants": rows}
    if device.type == "cuda":
        result["peak_memory_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
        try:  # diagnostics: a failure here keeps the timings above
            result["synchronising_calls_per_2_loop_steps"] = synchronising_calls(train_step, stream().__next__, 2)
            if args.profile:
                result["profile"] = {"real": profile(train_step, lambda: real, 3, Path(args.profile), "real"),
                                     "loop": profile(train_step, stream().__next__, 3, Path(args.profile), "loop")}
        except Exception as error:  # noqa: BLE001
            result["diagnostics_error"] = f"{type(error).__name__}: {error}"
            print("diagnostics failed:", result["diagnostics_error"])

    print(f"\n{cfg.name}, batch {args.batch_size}, {args.points} points, {'compiled' if args.compile else 'eager'}, "
          f"{result['machine'].get('gpu', result['machine']['cpu'])}")
    print("| variant | wall ms/step | host ms/step | samples/s |\n|---|---|---|---|")
    for name, row in rows.items():
        rate = f"{row['samples_per_s']:.1f}" if "samples_per_s" in row else "-"
        host = "-" if row["host_ms"] is None else f"{row['host_ms']:.1f}"
        print(f"| {name} | {row['wall_ms']:.1f} | {host} | {rate} |")
    for line in result.get("synchronising_calls_per_2_loop_steps", [])[:20]:
        print("sync:", line)
    for name, p in result.get("profile", {}).items():
        print(f"profile {name}: GPU busy {p['gpu_busy_ms_per_step']:.1f} ms/step")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
