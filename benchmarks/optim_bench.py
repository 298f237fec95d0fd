"""Optimiser state memory, step time and training loss: 8-bit LAMB (`Lamb8bit`) against 32-bit `Lamb`.

    python -m benchmarks.optim_bench [--device cuda] [--config rvt2] [--repeats 20]
                                     [--loss-config small] [--loss-steps 300] [--json out.json] [--quick]

State and speed: the parameters of the --config policy with fixed random gradients; the bytes of each
optimiser's state (per parameter too) and the median time of one step after warm-up, plain and as
`rvt2 train` calls it (with the device-side flag that skips non-finite steps).
Loss: the --loss-config policy trained from the same initial weights on the same synthetic batches
(`benchmarks.policy_bench.synthetic_batch`, a few cycled) with each optimiser, as `rvt2 train` steps
(all heads and losses, gradient clipping at 5, warmup-cosine schedule); both loss curves, their first
and last values and the largest relative difference of the smoothed curves (moving average), beside
that of 32-bit Lamb on the same batches in the reverse order (the noise of the comparison). The
renderer is the pure-torch reference backend, so this runs wherever torch does. --quick: the small
config for both parts and a few steps on the CPU (under a minute).
"""

import argparse
import json
import statistics

import torch

from benchmarks.machine import describe
from benchmarks.policy_bench import synthetic_batch, timer
from rvt2cli.model.config import get_config
from rvt2cli.model.loss import policy_loss
from rvt2cli.model.policy import RVT2Policy
from rvt2cli.train.lamb8bit import BLOCK_SIZE, Lamb8bit, optimizer_state_bytes
from rvt2cli.train.lamb import Lamb
from rvt2cli.train.optim import warmup_cosine

WEIGHT_DECAY = 1e-4


def make(name: str, params, lr: float, block_size: int):
    if name == "Lamb":
        return Lamb(params, lr=lr, weight_decay=WEIGHT_DECAY)
    return Lamb8bit(params, lr=lr, weight_decay=WEIGHT_DECAY, block_size=block_size)


def median_step_ms(optimizer, device, repeats: int, **step_args) -> float:
    times = []
    for i in range(repeats + 2):  # two warm-up steps
        start = timer(device)
        optimizer.step(**step_args)
        if i >= 2:
            times.append(timer(device) - start)
    return 1000 * statistics.median(times)


def state_and_speed(cfg, device, repeats: int, block_size: int) -> list[dict]:
    shapes = [p.shape for p in RVT2Policy(cfg).parameters()]
    g = torch.Generator().manual_seed(0)
    weights = [torch.randn(s, generator=g) * 0.02 for s in shapes]
    grads = [torch.randn(s, generator=g) * 1e-3 for s in shapes]
    results = []
    for name in ("Lamb", "Lamb8bit"):
        params = [torch.nn.Parameter(w.to(device)) for w in weights]
        for p, grad in zip(params, grads):
            p.grad = grad.to(device)
        optimizer = make(name, params, 3e-4, block_size)
        step_ms = median_step_ms(optimizer, device, repeats)
        # as `rvt2 train` calls it: with the device-side flag that skips non-finite steps
        skip_ms = median_step_ms(optimizer, device, repeats, skip=torch.zeros((), dtype=torch.bool, device=device))
        n = sum(p.numel() for p in params)
        state = optimizer_state_bytes(optimizer)
        results.append({"optimizer": name, "config": cfg.name, "params": n, "tensors": len(params), "state_bytes": state,
                        "state_bytes_per_param": state / n, "step_ms": step_ms, "step_ms_with_skip_flag": skip_ms})
        print(json.dumps(results[-1]), flush=True)
        del optimizer, params
    return results


def moving_average(values: list[float], window: int) -> list[float]:
    out, total = [], 0.0
    for i, v in enumerate(values):
        total += v - (values[i - window] if i >= window else 0.0)
        out.append(total / min(i + 1, window))
    return out


def loss_curve(cfg, device, name: str, steps: int, lr: float, batch: int, points: int, batches: int, block_size: int,
               reverse: bool = False) -> list[float]:
    torch.manual_seed(0)
    policy = RVT2Policy(cfg, render_backend="torch").to(device)
    optimizer = make(name, policy.parameters(), lr, block_size)
    schedule = warmup_cosine(optimizer, max(1, steps // 10), steps)
    data = [synthetic_batch(cfg, batch, points, device, seed=s) for s in range(batches)]
    if reverse:
        data.reverse()
    amp = device.type == "cuda"
    losses = []
    for step in range(steps):
        obs, target, bins, flags = data[step % batches]
        with torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=amp):
            out = policy(obs, target, bins, target)
        loss = policy_loss(out, target, bins, flags[:, 0], flags[:, 1], cfg.image_size, cfg.heatmap_sigma)["total"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 5.0)
        optimizer.step()
        schedule.step()
        losses.append(float(loss.detach()))
    return losses


def compare_losses(cfg, device, steps: int, lr: float, batch: int, points: int, batches: int, block_size: int) -> dict:
    """Both optimisers' loss curves, and as the yardstick of noise, 32-bit Lamb's on the same batches in
    the reverse order."""
    run = dict(steps=steps, lr=lr, batch=batch, points=points, batches=batches, block_size=block_size)
    curves = {name: loss_curve(cfg, device, name, **run) for name in ("Lamb", "Lamb8bit")}
    curves["Lamb, reversed batches"] = loss_curve(cfg, device, "Lamb", **run, reverse=True)
    window = max(1, steps // 10)
    smooth = {name: moving_average(c, window) for name, c in curves.items()}

    def relative(other: str) -> list[float]:
        return [abs(a - b) / abs(a) for a, b in zip(smooth["Lamb"], smooth[other])]

    return {"config": cfg.name, "steps": steps, "lr": lr, "batch": batch, "points": points, "batches": batches, "window": window,
            "first": {k: c[0] for k, c in curves.items()}, "last_smoothed": {k: s[-1] for k, s in smooth.items()},
            "max_rel_diff_smoothed": max(relative("Lamb8bit")), "final_rel_diff_smoothed": relative("Lamb8bit")[-1],
            "noise_max_rel_diff_smoothed": max(relative("Lamb, reversed batches")), "curves": curves}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--config", default="rvt2", help="model whose parameters the state and speed part uses")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--block-size", type=int, default=BLOCK_SIZE)
    parser.add_argument("--loss-config", default="small")
    parser.add_argument("--loss-steps", type=int, default=300)
    parser.add_argument("--lr", type=float, default=1e-3, help="peak learning rate of the loss comparison")
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--points", type=int, default=4000)
    parser.add_argument("--batches", type=int, default=4, help="distinct synthetic batches, cycled")
    parser.add_argument("--json")
    parser.add_argument("--quick", action="store_true", help="small config, few steps: checks that it runs")
    args = parser.parse_args()
    device = torch.device(args.device)
    config, repeats, loss_steps, batch, points = args.config, args.repeats, args.loss_steps, args.batch, args.points
    if args.quick:
        config, repeats, loss_steps, batch, points = "small", 2, 8, 2, 1000
    results = {"machine": describe(), "device": str(device), "block_size": args.block_size,
               "state": state_and_speed(get_config(config), device, repeats, args.block_size)}
    results["loss"] = compare_losses(get_config(args.loss_config), device, loss_steps, args.lr, batch, points, args.batches, args.block_size)
    loss = results["loss"]

    lamb = results["state"][0]
    print(f"\n{config}: {lamb['params'] / 1e6:.1f} M parameters in {lamb['tensors']} tensors, on {device}")
    print("\n| optimizer | state MiB | state bytes/param | step ms (median) | step ms, skip flag given |")
    print("|---|---|---|---|---|")
    for r in results["state"]:
        print(f"| {r['optimizer']} | {r['state_bytes'] / 2**20:.1f} | {r['state_bytes_per_param']:.3f} | {r['step_ms']:.1f} | "
              f"{r['step_ms_with_skip_flag']:.1f} |")
    print(f"\nLoss, {loss['config']} config, {loss['steps']} steps at peak lr {loss['lr']:g}, batch {loss['batch']} "
          f"(moving average over {loss['window']} steps):")
    print("\n| optimizer | first loss | last loss (smoothed) |")
    print("|---|---|---|")
    for name in loss["curves"]:
        print(f"| {name} | {loss['first'][name]:.4f} | {loss['last_smoothed'][name]:.4f} |")
    print(f"\nLamb8bit against Lamb, largest relative difference of the smoothed curves: {loss['max_rel_diff_smoothed']:.4f} "
          f"(at the end: {loss['final_rel_diff_smoothed']:.4f}); noise, Lamb on reversed batches: "
          f"{loss['noise_max_rel_diff_smoothed']:.4f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
