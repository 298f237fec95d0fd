"""Time the warp point renderer against the torch reference.

    python -m benchmarks.render_bench [--device cpu|cuda] [--quick] [--json OUT]

Clouds of B x N points uniform in the cube [-1, 1]^3 with 6 feature channels (xyz, rgb: what the
network renders), 3 orthographic views (top, front, right) at 224 x 224. Two modes:
"zbuffer+gather" (no splatting) and "full" (splat radius 1.5 px). Each time is the median over
repeated calls after two warm-up calls; on CUDA, CUDA events around back-to-back calls.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from rvt2cli.render import RVT2_VIEWS, cube_rig, render

IMAGE_SIZE = 224
SPLAT_PIXELS = 1.5
FULL_CASES = [(batch, n) for batch in (1, 24) for n in (20_000, 50_000, 200_000)]
QUICK_CASES = [(2, 2_000)]
MODES = {"zbuffer+gather": 0.0, "full": SPLAT_PIXELS * 2 / IMAGE_SIZE}  # splat radius, cube units


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--quick", action="store_true", help="one tiny case, runs in seconds (CI)")
    parser.add_argument("--json", type=Path, help="write the results and the machine description here")
    args = parser.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA device is available")

    device = torch.device(args.device)
    load_before = os.getloadavg()[0]
    rows = []
    for batch, n in QUICK_CASES if args.quick else FULL_CASES:
        points, features = cloud(batch, n, device)
        cameras = cube_rig(RVT2_VIEWS, IMAGE_SIZE, batch_size=batch, device=device)
        for mode, radius in MODES.items():
            def time_backend(backend: str) -> float:
                return median_ms(
                    lambda: render(points, features, cameras, IMAGE_SIZE, splat_radius=radius, backend=backend),
                    device,
                    args.quick,
                )

            warp_ms, torch_ms = time_backend("warp"), time_backend("torch")
            rows.append(
                dict(batch=batch, points=n, mode=mode, warp_ms=warp_ms, torch_ms=torch_ms, speedup=torch_ms / warp_ms)
            )
            print(f"  {batch:>3} x {n:>7,} {mode:<15} warp {warp_ms:9.3f} ms   torch {torch_ms:9.3f} ms", flush=True)

    machine = describe_machine(device)
    machine["load_average_1min"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]  # before, after
    print()
    print(markdown_table(rows, machine))
    if args.json:
        report = dict(machine=machine, image_size=IMAGE_SIZE, views=RVT2_VIEWS, splat_pixels=SPLAT_PIXELS, results=rows)
        args.json.write_text(json.dumps(report, indent=2) + "\n")


def cloud(batch: int, n: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    points = torch.rand(batch, n, 3, generator=g) * 2 - 1
    rgb = torch.rand(batch, n, 3, generator=g)
    return points.to(device), torch.cat([points, rgb], -1).to(device)


def median_ms(call: Callable[[], object], device: torch.device, quick: bool) -> float:
    """Median milliseconds per call after two warm-up calls (the first compiles or loads kernels)."""
    call()
    call()
    if device.type == "cuda":
        return _median_cuda_ms(call, samples=5 if quick else 20, calls_per_sample=10)
    samples: list[float] = []
    budget = 0.5 if quick else 3.0  # seconds: at least 3 samples, more while cheap
    while len(samples) < 3 or (sum(samples) < budget * 1000 and len(samples) < 25):
        start = time.perf_counter()
        call()
        samples.append((time.perf_counter() - start) * 1000)
    return statistics.median(samples)


def _median_cuda_ms(call: Callable[[], object], samples: int, calls_per_sample: int) -> float:
    times = []
    for _ in range(samples):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        for _ in range(calls_per_sample):
            call()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end) / calls_per_sample)
    return statistics.median(times)


def describe_machine(device: torch.device) -> dict:
    import warp

    return dict(
        device=device.type,
        cpu=cpu_model(),
        cpu_cores=os.cpu_count(),
        torch_threads=torch.get_num_threads(),
        gpu=torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        torch=torch.__version__,
        warp=warp.__version__,
        python=platform.python_version(),
        platform=platform.platform(),
    )


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def markdown_table(rows: list[dict], machine: dict) -> str:
    where = machine["gpu"] or f"{machine['cpu']}, {machine['cpu_cores']} cores"
    lines = [
        f"{len(RVT2_VIEWS)} views at {IMAGE_SIZE}x{IMAGE_SIZE}, {where}; "
        f"torch {machine['torch']}, warp {machine['warp']}",
        "",
        "| batch | points/cloud | mode | warp (ms) | torch reference (ms) | speedup |",
        "|---:|---:|---|---:|---:|---:|",
    ]
    for r in rows:
        cells = [r["batch"], f"{r['points']:,}", r["mode"], f"{r['warp_ms']:.3f}", f"{r['torch_ms']:.3f}"]
        cells.append(f"{r['speedup']:.1f}x")
        lines.append("| " + " | ".join(map(str, cells)) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
