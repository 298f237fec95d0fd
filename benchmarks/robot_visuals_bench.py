"""The lighter Panda against ManiSkill's (rvt2cli/record/robot_visuals.py): a capture's time with each, and
how many depth pixels of each camera the two differ in, in the same scene, under this machine's renderer.

    python -m benchmarks.robot_visuals_bench [--tasks turn_tap,insert_peg] [--captures 10] [--json out.json]

RVT2_VULKAN=lavapipe or nvidia picks the renderer. Recording's cost both ways: benchmarks/record_bench.py on
each tree (docs/BENCHMARKS.md, "Recording cost").
"""

import argparse
import json
import time

import numpy as np

from benchmarks.machine import describe
from rvt2cli.record.capture import capture_cameras
from rvt2cli.record.scene import make_env
from rvt2cli.runtime import use_vulkan_driver
from rvt2cli.tasks import get_task


def compare(task_name: str, captures: int, seed: int = 0) -> dict:
    """Mean capture time (ms, after the first) with each Panda, and each camera's share of depth pixels that
    differ by more than 1 mm between them."""
    views, ms = {}, {}
    for lighten in (True, False):
        env = make_env(get_task(task_name), lighten=lighten)
        env.reset(seed=seed)
        capture_cameras(env)   # the first capture compiles shaders
        start = time.perf_counter()
        for _ in range(captures):
            frames = capture_cameras(env)
        ms["lighter" if lighten else "maniskill"] = (time.perf_counter() - start) / captures * 1000
        views[lighten] = frames
        env.close()
    moved = {name: float((np.abs(views[True][name].depth - views[False][name].depth) > 0.001).mean())
             for name in views[True]}
    return {"task": task_name, "capture_ms": ms, "depth_moved_over_1mm": moved}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="turn_tap,insert_peg")
    parser.add_argument("--captures", type=int, default=10)
    parser.add_argument("--json")
    args = parser.parse_args()
    renderer = use_vulkan_driver().name
    rows = [compare(name, args.captures) for name in args.tasks.split(",")]
    print(f"renderer: {renderer}")
    print("| task | capture, lighter Panda (ms) | ManiSkill's Panda (ms) | depth pixels moved > 1 mm, per camera |")
    print("|---|---|---|---|")
    for row in rows:
        moved = ", ".join(f"{name} {share:.2%}" for name, share in row["depth_moved_over_1mm"].items())
        print(f"| {row['task']} | {row['capture_ms']['lighter']:.1f} | {row['capture_ms']['maniskill']:.1f} | {moved} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": describe(), "renderer": renderer, "tasks": rows}, f, indent=1)


if __name__ == "__main__":
    main()
