"""Several GPUs: `rvt2 train` under torchrun, its scaling and whether a killed run resumes exactly.

    python -m benchmarks.ddp_bench --data DEMOS [--gpus 2] [--batch-size 96] [--steps 120] [--config rvt2]
                                   [--compile] [--train-args "OPTIONS"] [--multi-gpu-run RUN_DIR] [--resume-check]
                                   [--resume-config small] [--json out.json]
    python -m benchmarks.ddp_bench --compare-losses ONE_GPU_RUN MULTI_GPU_RUN [--json out.json]

Scaling: the real training loop (`python -m torch.distributed.run -m rvt2cli train`, the command a user
runs) on 1 GPU and on --gpus GPUs at the same per-GPU batch; each run's samples/s is the median of its
logged intervals after the first two (compilation, warm-up), read from its train.csv. Reported: both
rates and their ratio (ideal: --gpus), and how many steps each run skipped as non-finite (a
several-GPU run that skips steps the one-GPU run does not is a bug; --train-args adds a recipe's
options, e.g. "--rotation-bins 360 --aim-held"). --multi-gpu-run takes the several-GPU rate from a finished run of
the same command (a full training run, say) instead of starting one.
Resume check (--resume-check): a short run of --resume-config on --gpus processes, three times: straight,
straight again (how far two identical runs on this hardware differ: GPU kernels with floating-point
atomics are not bitwise repeatable), and killed after its first checkpoint, then continued with only
`--resume`. Reported: the largest weight difference of each pair and whether the logged losses agree.
On CPUs (gloo) the same check is a unit test (tests/test_train.py), where it is exact.
Loss curves (--compare-losses): two finished runs at the same global batch, one GPU against several,
compared on their logged steps: the largest and mean gap between their smoothed curves (moving average
over --window rows), beside each run's own row-to-row noise around its smoothed curve. (Rank 0 logs
the loss of its own share of the batch, so a several-GPU run's rows are noisier by design.)
"""

import argparse
import csv
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.machine import describe
from rvt2cli.train.checkpoint import load_checkpoint


def train_command(processes: int, out: Path, args: list[str]) -> list[str]:
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(processes),
            "-m", "rvt2cli", "train", "--out", str(out), "--no-progress", *args]


def run(command: list[str]) -> None:
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        sys.exit(f"{' '.join(command)} failed:\n{result.stderr[-3000:]}")


def logged(run_dir: Path) -> list[dict]:
    with open(run_dir / "train.csv") as f:
        return list(csv.DictReader(f))


def steady_rate(run_dir: Path) -> float:
    rates = [float(row["samples_per_s"]) for row in logged(run_dir)[2:]]
    if not rates:
        sys.exit(f"{run_dir}: too few logged intervals for a rate; raise --steps")
    return statistics.median(rates)


def skipped_steps(run_dir: Path) -> int:
    """Steps the run skipped as non-finite, from its last logged row."""
    return int(logged(run_dir)[-1]["skipped"])


def scaling(data: list[str], gpus: int, config: str, batch: int, steps: int, compile: bool, work: Path,
            multi_gpu_run: Path | None, train_args: list[str]) -> dict:
    args = ["--data", *data, "--config", config, "--batch-size", str(batch), "--steps", str(steps), "--log-every", "10",
            "--val-episodes", "0", "--save-every", str(steps), "--warmup", "10"] + (["--compile"] if compile else [])
    args += train_args
    rates, skipped = {}, {}
    if multi_gpu_run is not None:
        rates[gpus], skipped[gpus] = steady_rate(multi_gpu_run), skipped_steps(multi_gpu_run)
        print(f"{gpus} GPUs ({multi_gpu_run}): {rates[gpus]:.0f} samples/s, {skipped[gpus]} non-finite steps", flush=True)
    for processes in [p for p in (1, gpus) if p not in rates]:
        started = time.perf_counter()
        run(train_command(processes, work / f"scale_{processes}", args))
        rates[processes] = steady_rate(work / f"scale_{processes}")
        skipped[processes] = skipped_steps(work / f"scale_{processes}")
        print(f"{processes} GPU(s), batch {batch} each: {rates[processes]:.0f} samples/s, {skipped[processes]} "
              f"non-finite steps skipped (run took {time.perf_counter() - started:.0f} s)", flush=True)
    return {"config": config, "batch_per_gpu": batch, "steps": steps, "compiled": compile, "train_args": train_args,
            "samples_per_s": {str(k): rates[k] for k in sorted(rates)}, "scaling": rates[gpus] / rates[1], "ideal": gpus,
            "skipped_steps": {str(k): skipped[k] for k in sorted(skipped)},
            "multi_gpu_run": str(multi_gpu_run) if multi_gpu_run else None}


def max_weight_difference(a: Path, b: Path) -> float:
    wa, wb = load_checkpoint(a).weights, load_checkpoint(b).weights
    return max(float((wa[k].float() - wb[k].float()).abs().max()) for k in wa)


def losses(run_dir: Path) -> list[tuple[str, str]]:
    return [(row["step"], row["loss"]) for row in logged(run_dir)]


def smoothed(values: list[float], window: int) -> list[float]:
    return [statistics.fmean(values[max(0, i - window + 1):i + 1]) for i in range(len(values))]


def compare_losses(one: Path, several: Path, window: int) -> dict:
    curves = {}
    for run_dir in (one, several):
        curves[run_dir] = {int(row["step"]): float(row["loss"]) for row in logged(run_dir)}
    steps = sorted(set(curves[one]) & set(curves[several]))
    raw = {k: [curves[k][s] for s in steps] for k in curves}
    smooth = {k: smoothed(v, window) for k, v in raw.items()}
    later = [i for i, s in enumerate(steps) if s > steps[-1] // 10]  # after warmup
    gap = [abs(smooth[one][i] - smooth[several][i]) for i in later]
    noise = {k: statistics.fmean(abs(raw[k][i] - smooth[k][i]) for i in later) for k in raw}
    tail = max(1, len(steps) // 10)
    result = {"one_gpu_run": str(one), "multi_gpu_run": str(several), "window_rows": window, "steps_compared": len(steps),
              "max_gap": max(gap), "mean_gap": statistics.fmean(gap),
              "row_noise": {"one_gpu": noise[one], "multi_gpu": noise[several]},
              "last_tenth_mean_loss": {"one_gpu": statistics.fmean(raw[one][-tail:]),
                                       "multi_gpu": statistics.fmean(raw[several][-tail:])}}
    print(json.dumps(result, indent=1), flush=True)
    return result


def resume_check(data: list[str], gpus: int, config: str, work: Path) -> dict:
    steps, every = 24, 8
    args = ["--data", *data, "--config", config, "--batch-size", "4", "--steps", str(steps), "--save-every", str(every),
            "--log-every", "1", "--warmup", "2", "--val-episodes", "0", "--max-points", "20000"]
    straight, again, killed = work / "straight", work / "again", work / "killed"
    run(train_command(gpus, straight, args))
    run(train_command(gpus, again, args))
    proc = subprocess.Popen(train_command(gpus, killed, args), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    deadline = time.time() + 600
    while not (killed / "last").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    killed_at = load_checkpoint(killed).info["step"]
    run(train_command(gpus, killed, ["--resume"]))
    result = {"config": config, "processes": gpus, "steps": steps, "killed_at_step": killed_at,
              "resumed_to_step": load_checkpoint(killed).info["step"],
              "max_weight_diff_straight_vs_again": max_weight_difference(straight, again),
              "max_weight_diff_straight_vs_resumed": max_weight_difference(straight, killed),
              "same_losses_straight_vs_again": losses(straight) == losses(again),
              "same_losses_straight_vs_resumed": losses(straight) == losses(killed)}
    print(json.dumps(result, indent=1), flush=True)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", help="recorded demos (with keyframes) or a sample cache")
    parser.add_argument("--compare-losses", nargs=2, type=Path, metavar=("ONE_GPU_RUN", "MULTI_GPU_RUN"),
                        help="only compare the loss curves of two finished runs")
    parser.add_argument("--window", type=int, default=10, help="--compare-losses: moving-average rows")
    parser.add_argument("--gpus", type=int, default=2)
    parser.add_argument("--config", default="rvt2")
    parser.add_argument("--batch-size", type=int, default=96, help="per GPU")
    parser.add_argument("--steps", type=int, default=120)
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--multi-gpu-run", type=Path, help="take the --gpus rate from this finished run's train.csv")
    parser.add_argument("--train-args", default="",
                        help="more rvt2 train options for the scaling runs, in one string (a recipe's options)")
    parser.add_argument("--skip-scaling", action="store_true")
    parser.add_argument("--resume-check", action="store_true")
    parser.add_argument("--resume-config", default="small")
    parser.add_argument("--work", help="folder for the runs (default: a temporary one)")
    parser.add_argument("--json")
    args = parser.parse_args()
    if args.compare_losses:
        result = {"losses": compare_losses(*args.compare_losses, args.window)}
        if args.json:
            Path(args.json).write_text(json.dumps(result, indent=1))
        return
    if not args.data:
        parser.error("--data is needed (unless --compare-losses)")
    if torch.cuda.is_available() and torch.cuda.device_count() < args.gpus:
        sys.exit(f"this machine has {torch.cuda.device_count()} GPU(s); --gpus {args.gpus} needs that many")
    gpus = [torch.cuda.get_device_name(i) for i in range(args.gpus)] if torch.cuda.is_available() else []
    work = Path(args.work or tempfile.mkdtemp(prefix="ddp_bench_"))
    work.mkdir(parents=True, exist_ok=True)
    report = {"machine": {**describe(), "gpus": gpus}}
    if args.resume_check:
        report["resume"] = resume_check(args.data, args.gpus, args.resume_config, work)
    if not args.skip_scaling:
        report["scaling"] = scaling(args.data, args.gpus, args.config, args.batch_size, args.steps, args.compile, work,
                                    args.multi_gpu_run, args.train_args.split())
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
