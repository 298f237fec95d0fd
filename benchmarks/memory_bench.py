"""Where the training samples live against the GPU memory and speed of `rvt2 train`, side by side.

    python -m benchmarks.memory_bench --data DEMOS|CACHE [--config rvt2] [--batch-size 192] [--micro-batch 48]
                                      [--steps 20] [--budget-gib 24] [--eager] [--json out.json] [--quick]

`rvt2 train` itself (`rvt2cli.train.trainer.train`, compiled and in bf16 on a GPU, validation off), three
times on one read of the samples:
  device        the clouds on the GPU (`--samples-on device`), the whole batch in one pass
  host          the clouds on the host (`--samples-on host`): each batch's rows gathered into pinned memory
                and copied beside the step (rvt2cli.train.clouds)
  host+micro    the clouds on the host and the batch in parts of --micro-batch (`--micro-batch`): the same
                step in the memory of a smaller GPU
For each: samples/s over the second half of 2 x --steps steps (the first includes compiling, as in
benchmarks/loop_bench.py), torch.cuda.max_memory_allocated over the run, the clouds' bytes on the GPU
and on the host, the pinned staging buffers, and whether the peak fits --budget-gib (on a card of that
size, the CUDA context and the allocator's slack, about 1 GiB, come on top of it).
"""

import argparse
import gc
import json
import tempfile
from dataclasses import replace
from pathlib import Path

import torch

from benchmarks.machine import describe
from rvt2cli.model.config import get_config
from rvt2cli.train.clouds import StagedRows
from rvt2cli.train.trainer import TrainOptions, train
from rvt2cli.train.training_data import TrainingData, read_data

GIB = 2**30


def with_clouds_on(data: TrainingData, on_host: bool, device: torch.device) -> TrainingData:
    """The same samples with their clouds on the host or on `device` (what `--samples-on` packs)."""
    packed = data.packed
    where = torch.device("cpu") if on_host else device
    return replace(data, packed=replace(packed, xyz=packed.xyz.to(where), rgb=packed.rgb.to(where), clouds_on_host=on_host))


def run_variant(opts: TrainOptions, data: TrainingData, steps: int, device: torch.device) -> dict:
    """`rvt2 train` for 2 x `steps` steps on `data`: its rate over the second half, and its memory."""
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
    torch._dynamo.reset()   # each variant compiles its own policy, as a fresh run does
    run = train(replace(opts, steps=2 * steps, warmup=1, log_every=steps, save_every=2 * steps), say=lambda *_: None,
                data=data)
    packed = data.packed
    clouds = packed.xyz.nbytes + packed.rgb.nbytes
    rows = opts.micro_batch or opts.batch_size
    row = {"samples_per_s": run.samples_per_s, "batch": opts.batch_size, "micro_batch": opts.micro_batch,
           "clouds_on": "host" if packed.clouds_on_host else device.type,
           "clouds_gpu_gib": 0.0 if packed.clouds_on_host or device.type != "cuda" else clouds / GIB,
           "clouds_host_gib": clouds / GIB if packed.clouds_on_host or device.type != "cuda" else 0.0,
           "pinned_staging_gib": (StagedRows.BUFFERS * rows * clouds / len(packed) / GIB
                                  if packed.clouds_on_host and device.type == "cuda" else 0.0),
           "skipped_steps": run.skipped_steps}
    if device.type == "cuda":
        row["peak_gib"] = torch.cuda.max_memory_allocated(device) / GIB
        row["peak_without_clouds_gib"] = row["peak_gib"] - row["clouds_gpu_gib"]
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", required=True, help="annotated episodes (files or folders) or one sample cache")
    parser.add_argument("--config", default="rvt2")
    parser.add_argument("--batch-size", type=int, default=192)
    parser.add_argument("--micro-batch", type=int, default=48, help="the parts of host+micro (default 48: rvt2 in 24 GB)")
    parser.add_argument("--points", type=int, default=50_000)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--budget-gib", type=float, default=24.0, help="the GPU memory host+micro should fit")
    parser.add_argument("--eager", action="store_true", help="do not compile the network (compiled by default, as trained)")
    parser.add_argument("--variants", default="device,host,host+micro")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--quick", action="store_true", help="a tiny configuration on the CPU: checks that it runs")
    args = parser.parse_args()
    if args.quick:
        args.config, args.batch_size, args.micro_batch, args.points, args.steps, args.eager = "small", 4, 2, 2000, 2, True
    device = torch.device(args.device)
    opts = TrainOptions(data=args.data, out=tempfile.mkdtemp(prefix="memory_bench_"), config=args.config,
                        batch_size=args.batch_size, max_points=args.points, val_episodes=0, progress=False,
                        compile=not args.eager, device=str(device), samples_on="host")
    data = read_data(opts, get_config(args.config), device, progress=False, resume=None, say=print)
    variants = {"device": (False, None), "host": (True, None), "host+micro": (True, args.micro_batch)}
    rows = {}
    for name in args.variants.split(","):
        on_host, micro = variants[name]
        rows[name] = run_variant(replace(opts, out=str(Path(opts.out) / name), micro_batch=micro, samples_on="host" if on_host else "device"),
                                 with_clouds_on(data, on_host, device), args.steps, device)
        print(name, json.dumps(rows[name]), flush=True)

    machine = describe()
    print(f"\n{args.config}, batch {args.batch_size}, {args.points} points, {len(data.packed)} samples, "
          f"{'eager' if args.eager else 'compiled'}, {machine.get('gpu', machine['cpu'])}")
    print("| variant | samples/s | peak GiB (max_memory_allocated) | less the clouds | clouds on GPU / host GiB | pinned staging GiB |")
    print("|---|---|---|---|---|---|")
    for name, row in rows.items():
        peak = f"{row['peak_gib']:.1f}" if "peak_gib" in row else "-"
        less = f"{row['peak_without_clouds_gib']:.1f}" if "peak_gib" in row else "-"
        label = name + (f" ({row['micro_batch']})" if row["micro_batch"] else "")
        print(f"| {label} | {row['samples_per_s']:.1f} | {peak} | {less} | {row['clouds_gpu_gib']:.2f} / "
              f"{row['clouds_host_gib']:.2f} | {row['pinned_staging_gib']:.2f} |")
    if "host" in rows and "device" in rows:
        print(f"host / device speed: {rows['host']['samples_per_s'] / rows['device']['samples_per_s']:.3f}")
    if "host+micro" in rows and "peak_gib" in rows["host+micro"]:
        fits = rows["host+micro"]["peak_gib"] <= args.budget_gib - 1.0
        print(f"host+micro peak {rows['host+micro']['peak_gib']:.1f} GiB: {'fits' if fits else 'does not fit'} "
              f"{args.budget_gib:g} GiB less 1 GiB of context and slack")
    result = {"machine": machine, "device": str(device), "config": args.config, "batch": args.batch_size,
              "points": args.points, "samples": len(data.packed), "steps": args.steps, "compiled": not args.eager,
              "budget_gib": args.budget_gib, "variants": rows}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
