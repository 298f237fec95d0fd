"""The training step's matrix products alone, in bf16 and in FP8: what FP8 could save at our shapes.

    python -m benchmarks.gemm_bench [--config rvt2] [--batch 192] [--json out.json] [--quick]

The products are found, not listed: one forward of the policy at --batch (synthetic clouds, bf16 autocast on
CUDA) under a dispatch mode that records the shape (M, K, N) of every matrix product it runs (`aten.mm`,
`aten.addmm`: linear layers, `F.linear` on slices of a weight included; the 1x1 convolutions are not among
them). Each shape is then timed as a training step runs it, forward plus the two products of its backward
(the input's gradient, M x N by N x K, and the weight's, K x M by M x N):

- bf16: `torch.mm`;
- FP8 (CUDA, Hopper or newer): `torch._scaled_mm` on operands already cast, e4m3 forward and e5m2 for the
  gradient, one scale per tensor. That is the ceiling of FP8 training at these shapes: torchao's Float8Linear
  also pays for finding each operand's scale and casting it, timed apart here (`cast_ms`, eager) as what a
  compiled step would have to fuse away.

A table per shape (count per step, TFLOP/s in each precision) and the totals per training step.
"""

import argparse
import json
from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from benchmarks.machine import describe
from benchmarks.policy_bench import median_time_ms, synthetic_batch
from rvt2cli.model.config import get_config
from rvt2cli.model.policy import RVT2Policy

_PRODUCTS = {torch.ops.aten.mm.default: (0, 1), torch.ops.aten.addmm.default: (1, 2)}


class _ProductShapes(TorchDispatchMode):
    """Counts the (M, K, N) of every 2-D matrix product run inside it."""

    def __init__(self):
        super().__init__()
        self.shapes: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func in _PRODUCTS:
            a, b = (args[i] for i in _PRODUCTS[func])
            self.shapes[(a.shape[0], a.shape[1], b.shape[1])] += 1
        return func(*args, **(kwargs or {}))


def product_shapes(cfg, batch: int, points: int, device) -> Counter:
    """(M, K, N) -> how many times one forward of the policy at `batch` runs that product."""
    policy = RVT2Policy(cfg, render_backend="warp").to(device)
    obs, target, bins, _ = synthetic_batch(cfg, batch, points, device)
    recorder = _ProductShapes()
    with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"), recorder:
        policy(obs, target, bins, target)
    return recorder.shapes


def _three_products(m: int, k: int, n: int, device):
    """The forward product and the two of its backward: (left, right, left's FP8 type, right's), operands in
    bf16. Activations and weights take e4m3, the output's gradient e5m2 (its wider range)."""
    e4m3, e5m2 = torch.float8_e4m3fn, torch.float8_e5m2
    x = torch.randn(m, k, device=device, dtype=torch.bfloat16)
    w = torch.randn(k, n, device=device, dtype=torch.bfloat16)
    grad = torch.randn(m, n, device=device, dtype=torch.bfloat16)
    return [(x, w, e4m3, e4m3), (grad, w.t().contiguous(), e5m2, e4m3), (x.t().contiguous(), grad, e4m3, e5m2)]


def _to_float8(t: torch.Tensor, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    scale = torch.finfo(dtype).max / t.abs().max().float().clamp(min=1e-12)
    return (t.float() * scale).to(dtype), scale.reciprocal()


def time_shape(m: int, k: int, n: int, device, repeats: int) -> dict:
    products = _three_products(m, k, n, device)
    result = {"m": m, "k": k, "n": n, "bf16_ms": sum(median_time_ms(lambda a=a, b=b: torch.mm(a, b), device, repeats)
                                                      for a, b, _, _ in products)}
    if device.type == "cuda" and torch.cuda.get_device_capability(device) >= (8, 9) and m % 16 == k % 16 == n % 16 == 0:
        fp8_ms = cast_ms = 0.0
        for a, b, left, right in products:
            (qa, sa), (qb, sb) = _to_float8(a, left), _to_float8(b.t().contiguous(), right)
            qb = qb.t()   # column-major, as _scaled_mm takes its right operand
            fp8_ms += median_time_ms(lambda: torch._scaled_mm(qa, qb, scale_a=sa, scale_b=sb, out_dtype=torch.bfloat16),
                                 device, repeats)
            cast_ms += median_time_ms(lambda: (_to_float8(a, left), _to_float8(b, right)), device, repeats)
        result |= {"fp8_ms": fp8_ms, "cast_ms": cast_ms}
    flops = 3 * 2 * m * k * n
    for key in ("bf16", "fp8"):
        if f"{key}_ms" in result:
            result[f"{key}_tflops"] = flops / (result[f"{key}_ms"] / 1000) / 1e12
    return result


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--config", default="rvt2")
    parser.add_argument("--batch", type=int, default=192, help="the training batch (per GPU)")
    parser.add_argument("--points", type=int, default=50_000)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--json")
    parser.add_argument("--quick", action="store_true", help="small config, tiny sizes: checks that it runs")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    config, batch, points, repeats = args.config, args.batch, args.points, args.repeats
    if args.quick:
        config, batch, points, repeats = "small", 2, 2000, 2
    shapes = product_shapes(get_config(config), batch, points, device)
    rows = [time_shape(m, k, n, device, repeats) | {"count": count} for (m, k, n), count in sorted(shapes.items())]
    totals = {"bf16_ms": sum(r["bf16_ms"] * r["count"] for r in rows)}
    if any("fp8_ms" in r for r in rows):   # shapes FP8 cannot take (a side not a multiple of 16) stay in bf16
        totals["fp8_ms"] = sum(r.get("fp8_ms", r["bf16_ms"]) * r["count"] for r in rows)
        totals["cast_ms"] = sum(r.get("cast_ms", 0.0) * r["count"] for r in rows)
    print("| M | K | N | per step | bf16 ms (3 products) | bf16 TFLOP/s | fp8 ms | fp8 TFLOP/s | cast ms |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['m']} | {r['k']} | {r['n']} | {r['count']} | {r['bf16_ms']:.3f} | {r['bf16_tflops']:.0f} | "
              f"{r.get('fp8_ms', float('nan')):.3f} | {r.get('fp8_tflops', float('nan')):.0f} | {r.get('cast_ms', float('nan')):.3f} |")
    print("per training step: " + ", ".join(f"{k} {v:.1f}" for k, v in totals.items()))
    results = {"machine": describe(), "device": str(device), "config": config, "batch": batch, "points": points,
               "shapes": rows, "per_step": totals}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)
    return results


if __name__ == "__main__":
    main()
