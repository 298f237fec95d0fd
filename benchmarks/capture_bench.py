"""How fast the four cameras are captured: rvt2's `capture_cameras` against SAPIEN's camera groups, which
render every camera of one or several scenes in one submission and hand the pictures over in CUDA memory.

    python -m benchmarks.capture_bench [--task open_drawer] [--captures 48] [--processes 1,8,15]
                                       [--scenes 1,8] [--variants cameras,group] [--json out.json]

Variants (each process builds `scenes` scenes of the task, runs the expert once in each for states, then
restores those states one after another and captures; only the captures are timed):
- cameras: `rvt2cli.record.capture.capture_camera_by_camera`, ManiSkill's way, scene by scene;
- group: `rvt2cli.record.capture.CameraGroup` over the process's scenes: one submission for all their
  cameras, the render transforms computed on the GPU from one CUDA buffer of poses (with one scene, what
  `capture_cameras` does where SAPIEN renders through CUDA).
Every variant's pictures are compared with camera-by-camera captures at the same states in scenes of their
own (colour levels, depth in mm), so a faster path that draws something else is seen. Captures per second
count four-camera captures: with `scenes` K, one round of the group is K captures. The group needs NVIDIA's
Vulkan driver and CUDA; elsewhere it reports why it did not run. (Updating the scenes' transforms on the
CPU and only taking the group's pictures draws stale transforms: once in a group, a scene takes them from
the GPU.)
"""

import argparse
import json
import multiprocessing
import os
import time
import traceback
from pathlib import Path

import numpy as np

TEXTURES = ("Color", "Position", "Segmentation")


def episode_states(env, task, seed: int, every: int = 3, most: int = 48) -> list[dict]:
    """Simulator states along the task's expert demo from `seed` (the scene stays as the expert left it)."""
    from rvt2cli.record.expert import run_expert
    from rvt2cli.tasks import episode_variation

    run = run_expert(env, task.expert, seed, max_frames=task.max_steps, variation=episode_variation(seed, task.variation_choices()))
    return [frame.sim for frame in run.frames[::every]][:most]


def compare(reference: dict, frames: dict) -> dict:
    """How far one capture's pictures are from camera-by-camera ones at the same state, over its cameras."""
    worst = {"colour_levels_max": 0, "colour_pixels_off": 0.0, "depth_mm_max": 0.0, "depth_pixels_over_1mm": 0.0}
    for name, ref in reference.items():
        got = frames[name]
        colour = np.abs(ref.rgb.astype(np.int32) - got.rgb.astype(np.int32))
        both = (ref.depth > 0) & (got.depth > 0)
        depth = np.abs(ref.depth - got.depth) * 1000.0
        worst["colour_levels_max"] = max(worst["colour_levels_max"], int(colour.max()))
        worst["colour_pixels_off"] = max(worst["colour_pixels_off"], float((colour.max(-1) > 1).mean()))
        worst["depth_mm_max"] = max(worst["depth_mm_max"], float(depth[both].max()) if both.any() else 0.0)
        worst["depth_pixels_over_1mm"] = max(worst["depth_pixels_over_1mm"],
                                             float(((depth > 1.0) | ((ref.depth > 0) != (got.depth > 0))).mean()))
    return worst


def measure(variant: str, task_name: str, scenes: int, captures: int, process: int, barrier=None, check: bool = False) -> dict:
    """One process's part: build `scenes` scenes, capture `captures` times (rounds of `scenes`), timed after the barrier."""
    from rvt2cli.record.capture import CameraGroup, capture_camera_by_camera
    from rvt2cli.record.scene import make_env, restore_sim_state
    from rvt2cli.tasks import get_task

    task = get_task(task_name)
    out = {"variant": variant, "scenes": scenes, "process": process}
    try:
        envs = [make_env(task) for _ in range(scenes)]
        seeds = [1000 * process + i for i in range(scenes)]
        states = [episode_states(env, task, seed) for seed, env in zip(seeds, envs)]
        rounds = max(1, captures // scenes)
        if variant == "cameras":
            def capture_round():
                return [capture_camera_by_camera(env) for env in envs]
        else:
            capture_round = CameraGroup(envs).capture

        def restore(k):
            for env, own in zip(envs, states):
                restore_sim_state(env, own[k % len(own)])

        for k in range(3):  # shaders compile at the first captures
            restore(k)
            capture_round()
        if check:
            out["versus_cameras"] = check_against_cameras(task, seeds, envs, states, capture_round)
        if barrier is not None:
            barrier.wait()
        start, spent = time.perf_counter(), 0.0
        for k in range(rounds):
            restore(k)
            t = time.perf_counter()
            capture_round()
            spent += time.perf_counter() - t
        out.update(start=start, end=time.perf_counter(), captures=rounds * scenes, capture_s=spent)
        for env in envs:
            env.close()
    except Exception as e:  # noqa: BLE001 - a variant this machine cannot run is reported, not fatal
        out["error"] = f"{type(e).__name__}: {e}"
        out["traceback"] = traceback.format_exc(limit=4)
        if barrier is not None:
            barrier.abort()
    return out


def check_against_cameras(task, seeds, envs, states, capture_round, samples: int = 6) -> dict:
    """The variant's pictures against camera-by-camera ones in scenes of their own, rebuilt from the same seeds."""
    from rvt2cli.record.capture import capture_camera_by_camera
    from rvt2cli.record.scene import make_env, restore_sim_state, set_variation
    from rvt2cli.tasks import episode_variation

    worst: dict = {}
    references = []
    for seed in seeds:
        ref = make_env(task)
        set_variation(ref, episode_variation(seed, task.variation_choices()))
        ref.reset(seed=seed)
        references.append(ref)
    for k in range(0, min(len(s) for s in states), max(1, min(len(s) for s in states) // samples)):
        for env, ref, own in zip(envs, references, states):
            restore_sim_state(env, own[k])
            restore_sim_state(ref, own[k])
        for ref, frames in zip(references, capture_round()):
            for key, value in compare(capture_camera_by_camera(ref), frames).items():
                worst[key] = max(worst.get(key, 0), value)
    for ref in references:
        ref.close()
    return worst


def _run(args):
    return measure(*args)


def concurrent(variant: str, task: str, scenes: int, captures: int, processes: int) -> dict:
    """`processes` processes capturing at once: captures per second over the span from the first start to the last end."""
    context = multiprocessing.get_context("spawn")
    with context.Manager() as manager:
        barrier = manager.Barrier(processes)
        with context.Pool(processes) as pool:
            parts = pool.map(_run, [(variant, task, scenes, captures, p, barrier, p == 0) for p in range(processes)])
    errors = [p["error"] for p in parts if "error" in p]
    if errors:
        return {"variant": variant, "scenes": scenes, "processes": processes, "error": errors[0],
                "traceback": next(p.get("traceback") for p in parts if "error" in p)}
    span = max(p["end"] for p in parts) - min(p["start"] for p in parts)
    total = sum(p["captures"] for p in parts)
    return {"variant": variant, "scenes": scenes, "processes": processes, "captures": total, "seconds": span,
            "captures_per_s": total / span, "ms_per_capture_in_process": 1000 * np.mean([p["capture_s"] / p["captures"] for p in parts]),
            "versus_cameras": parts[0].get("versus_cameras")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="open_drawer")
    parser.add_argument("--captures", type=int, default=48, help="four-camera captures per process")
    parser.add_argument("--processes", default="1,8,15")
    parser.add_argument("--scenes", default="1,8", help="scenes per process (for the group variants)")
    parser.add_argument("--variants", default="cameras,group")
    parser.add_argument("--json")
    args = parser.parse_args()
    from benchmarks.machine import describe
    from rvt2cli.runtime import use_vulkan_driver

    driver = use_vulkan_driver().name  # chosen once, inherited by the processes
    results = {"machine": describe(), "renderer": driver, "task": args.task, "runs": []}
    print(f"{args.task}, renderer {driver}, {args.captures} captures per process")
    print("| variant | scenes/process | processes | captures/s | ms per capture in a process | vs camera by camera |")
    print("|---|---|---|---|---|---|")
    for variant in args.variants.split(","):
        for scenes in [int(s) for s in args.scenes.split(",")] if variant != "cameras" else [1]:
            for processes in [int(p) for p in args.processes.split(",")]:
                r = concurrent(variant, args.task, scenes, args.captures, processes)
                results["runs"].append(r)
                if "error" in r:
                    print(f"| {variant} | {scenes} | {processes} | did not run: {r['error'][:120]} | | |", flush=True)
                    break
                check = r["versus_cameras"]
                versus = (f"colour <= {check['colour_levels_max']} levels ({check['colour_pixels_off']:.2%} of pixels > 1), "
                          f"depth <= {check['depth_mm_max']:.2f} mm ({check['depth_pixels_over_1mm']:.2%} > 1 mm)"
                          if check else "")
                print(f"| {variant} | {scenes} | {processes} | {r['captures_per_s']:.1f} | {r['ms_per_capture_in_process']:.1f} | "
                      f"{versus} |", flush=True)
                if args.json:
                    Path(args.json).write_text(json.dumps(results, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
