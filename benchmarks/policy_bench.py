"""Policy speed: training throughput and inference latency, rvt2 against the RVT-1-like ablation.

    python -m benchmarks.policy_bench [--device cuda] [--configs rvt2,rvt] [--batch 24] [--points 50000]
                                      [--json out.json] [--quick]

Training: the whole step (render both stages, forward, all heads and losses, backward, clipping,
optimizer: the `TrainStep` that `rvt2 train` runs) at batch --batch in bf16 (CUDA) with our 8-bit LAMB; samples/s
and peak GPU memory. Inference: batch 1, the full policy step (cloud in -> both stages rendered ->
network -> 3D argmax -> pose out), eager and as one CUDA graph; fps as the median over many steps
after warm-up, and the graph's outputs compared with the eager ones. Synthetic clouds of uniform
points: speed depends on sizes, not content. --quick runs a tiny CPU configuration (CI).
"""

import argparse
import json
import statistics
import time

import torch

from benchmarks.machine import describe
from rvt2cli.model.config import get_config
from rvt2cli.model.observation import Observation
from rvt2cli.model.policy import RVT2Policy
from rvt2cli.model.rotation import bin_centre_deg
from rvt2cli.train.batches import Batch
from rvt2cli.train.optim import make_optimizer, warmup_cosine
from rvt2cli.train.step import TrainStep


def synthetic_batch(cfg, batch: int, points: int, device, seed: int = 0):
    g = torch.Generator(device="cpu").manual_seed(seed)
    obs = Observation(points=(torch.rand(batch, points, 3, generator=g) * 2 - 1), rgb=torch.rand(batch, points, 3, generator=g),
                      num_points=torch.full((batch,), points), proprio=torch.randn(batch, cfg.proprio_dim, generator=g),
                      lang=torch.randn(batch, cfg.lang_tokens, cfg.lang_dim, generator=g)).to(device)
    target = (torch.rand(batch, 3, generator=g) * 1.6 - 0.8).to(device)
    bins = torch.randint(0, cfg.rotation_bins, (batch, 3), generator=g).to(device)
    flags = torch.randint(0, 2, (batch, 2), generator=g).to(device)
    return obs, target, bins, flags


def synthetic_train_batch(cfg, batch: int, points: int, device) -> Batch:
    """A training batch of synthetic clouds, stage 2 centred on the target."""
    obs, target, bins, flags = synthetic_batch(cfg, batch, points, device)
    euler_deg = bin_centre_deg(bins.float(), cfg.rotation_bins)
    return Batch(obs=obs, position=target, tcp_position=target, rot_bins=bins, euler_deg=euler_deg, gripper=flags[:, 0], collision=flags[:, 1],
                 quaternion=None, half=None, stage2_center=target)


def timer(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()


def median_time_ms(fn, device, repeats: int, warmup: int = 3) -> float:
    """The median of `repeats` timed calls of `fn`, after `warmup` untimed ones (the GPU synchronised)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = timer(device)
        fn()
        times.append(timer(device) - start)
    return 1000 * statistics.median(times)


def train_throughput(cfg, device, batch: int, points: int, steps: int, warmup: int, compile: bool = False,
                     eight_bit: bool = True, profile: str | None = None, compile_mode: str | None = None) -> dict:
    """The training step `rvt2 train` runs (rvt2cli.train.step.TrainStep), on one synthetic batch."""
    policy = RVT2Policy(cfg, render_backend="warp").to(device)
    if compile:
        policy.compile_network(compile_mode)
    optimizer, name = make_optimizer(policy.parameters(), 3e-4, 1e-4, device, eight_bit)
    schedule = warmup_cosine(optimizer, 10, 10_000)
    data = synthetic_train_batch(cfg, batch, points, device)
    train_step = TrainStep(policy, optimizer, schedule, amp=device.type == "cuda", clip=5.0)
    amp = device.type == "cuda"

    def step():
        train_step(data)

    for _ in range(warmup):
        step()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    start = timer(device)
    for _ in range(steps):
        step()
    seconds = (timer(device) - start) / steps
    result = {"config": cfg.name, "batch": batch, "points": points, "optimizer": name, "bf16": amp, "compiled": compile,
              "compile_mode": compile_mode or "default", "step_ms": 1000 * seconds, "samples_per_s": batch / seconds,
              "params_m": sum(p.numel() for p in policy.parameters()) / 1e6}
    if device.type == "cuda":
        result["peak_memory_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
    if profile:
        result["profile"] = profile_steps(step, device, profile)
    return result


def profile_steps(step, device, path: str, steps: int = 5, rows: int = 40) -> str:
    """Where the step's device time goes: torch.profiler over a few steps, kernels by total time (a table
    written to `path`, its head printed)."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        for _ in range(steps):
            step()
        timer(device)
    key = "cuda_time_total" if device.type == "cuda" else "cpu_time_total"
    table = prof.key_averages().table(sort_by=key, row_limit=rows, max_name_column_width=70)
    with open(path, "w") as f:
        f.write(f"{steps} steps\n{table}")
    print("\n".join(table.splitlines()[:25]))
    return path


def forward_flops(cfg, device, points: int) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    policy = RVT2Policy(cfg, render_backend="warp").to(device)
    obs, target, bins, _ = synthetic_batch(cfg, 1, points, device)
    counter = FlopCounterMode(display=False)
    with counter, torch.no_grad():
        policy(obs, target, bins, target)
    return float(counter.get_total_flops())


def inference_latency(cfg, device, points: int, repeats: int, compile: bool = False) -> dict:
    policy = RVT2Policy(cfg, render_backend="warp").to(device).eval()
    if compile:
        policy.compile_network()
    obs, _, _, _ = synthetic_batch(cfg, 1, points, device, seed=1)
    amp = device.type == "cuda"

    def eager():
        with torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=amp):
            pred = policy.predict(obs)
        return pred.position, pred.rot_bins, pred.gripper_open, pred.ignore_collisions

    def median_ms(fn) -> float:
        return median_time_ms(fn, device, repeats)

    result = {"config": cfg.name, "points": points, "compiled": compile, "eager_ms": median_ms(eager)}
    result["eager_fps"] = 1000 / result["eager_ms"]
    if device.type == "cuda":
        from rvt2cli.model.graphed import GraphedPredictor

        graphed = GraphedPredictor(policy, points)
        result["graph_ms"] = median_ms(lambda: graphed(obs))
        result["graph_fps"] = 1000 / result["graph_ms"]
        want, got = eager(), graphed(obs)
        result["graph_max_position_diff"] = float((want[0].float() - got[0].float()).abs().max())
        result["graph_same_bins"] = bool(torch.equal(want[1], got[1]))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--configs", default="rvt2,rvt")
    parser.add_argument("--batch", default="24", help="training batch size(s), comma-separated, e.g. 24,192")
    parser.add_argument("--points", type=int, default=50_000)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--skip-train", action="store_true")
    parser.add_argument("--skip-inference", action="store_true")
    parser.add_argument("--compile", action="store_true", help="torch.compile the network (training and inference)")
    parser.add_argument("--compile-mode", choices=("reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs"),
                        help="with --compile, the training step's torch.compile mode (default: torch's default); "
                             "reduce-overhead replays each compiled part as a CUDA graph")
    parser.add_argument("--profile", help="also profile the training step and write the kernel table here")
    parser.add_argument("--json")
    parser.add_argument("--quick", action="store_true", help="small config, tiny sizes: checks that it runs")
    args = parser.parse_args()
    device = torch.device(args.device)
    configs, points, steps, repeats = args.configs.split(","), args.points, args.steps, args.repeats
    batches = [int(b) for b in args.batch.split(",")]
    if args.quick:
        configs, batches, points, steps, repeats = ["small"], [2], 2000, 2, 3
    results = {"machine": describe(), "device": str(device), "train": [], "inference": [], "flops": {}}
    for name in configs:
        cfg = get_config(name)
        results["flops"][name] = forward_flops(cfg, device, points)
        for batch in [] if args.skip_train else batches:
            results["train"].append(train_throughput(cfg, device, batch, points, steps, warmup=3, compile=args.compile, profile=args.profile,
                                                    compile_mode=args.compile_mode))
            print(json.dumps(results["train"][-1]), flush=True)
        if not args.skip_inference:
            results["inference"].append(inference_latency(cfg, device, points, repeats, compile=args.compile))
            print(json.dumps(results["inference"][-1]), flush=True)
    print("\n| config | train samples/s | step ms | peak GiB | infer eager fps | infer graph fps | GFLOPs fwd/sample |")
    print("|---|---|---|---|---|---|---|")
    for name in configs:
        t = next((r for r in results["train"] if r["config"] == name), {})
        i = next((r for r in results["inference"] if r["config"] == name), {"eager_fps": float("nan")})
        print(f"| {name} | {t.get('samples_per_s', float('nan')):.1f} | {t.get('step_ms', float('nan')):.1f} | "
              f"{t.get('peak_memory_gib', float('nan')):.1f} | {i['eager_fps']:.1f} | {i.get('graph_fps', float('nan')):.1f} | "
              f"{results['flops'][name] / 1e9:.1f} |")
    if len(configs) == 2 and results["train"] and results["inference"]:
        a, b = (next(r for r in results["train"] if r["config"] == c) for c in configs)
        ia, ib = (next(r for r in results["inference"] if r["config"] == c) for c in configs)
        key = "graph_fps" if "graph_fps" in ia else "eager_fps"
        results["ablation"] = {"train_speedup": a["samples_per_s"] / b["samples_per_s"], "inference_speedup": ia[key] / ib[key]}
        print(f"\n{configs[0]} vs {configs[1]}: training {results['ablation']['train_speedup']:.2f}x, inference {results['ablation']['inference_speedup']:.2f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
