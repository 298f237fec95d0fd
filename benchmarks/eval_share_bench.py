"""An evaluation's workers sharing one policy against a policy in each worker (eager, and on CUDA replayed as a CUDA
graph): GPU memory, speed, outcomes.

    python -m benchmarks.eval_share_bench (--checkpoint RUN | --random rvt2) --tasks push_cube,stack_cube
        [--episodes 4] [--seed 20000] [--workers 14] [--device cuda] [--keyframe-budget 25] [--json out.json]

Runs `evaluate` (what `rvt2 eval` runs) on the same seeds (from 20000: validation seeds, since its result may choose
how the reported seeds are evaluated): each worker process loading the checkpoint on
--device (the default), then `--shared-policy` (the checkpoint loaded once, in the main process, answering
every worker's keyframe requests over the loopback, batched), then on a CUDA device `--cuda-graph` (each
worker's step replayed as one CUDA graph). While each runs, nvidia-smi is read every half second: the GPU
memory in use (its peak above what was in use before) and, where the machine lists them, the processes holding
some. Reports episodes per minute, keyframes per second, and how many episodes of each other way ended as with
a policy per worker (all of them on the CPU; on a GPU a batched forward may differ from a lone one in the last
bits, and the graph must not). `--random CONFIG`: a checkpoint of that config with random weights (speed and memory depend on
sizes; its episodes mostly run out of keyframes).
"""

import argparse
import json
import subprocess
import tempfile
import threading
import time
from pathlib import Path

from benchmarks.machine import describe
from benchmarks.serve_bench import random_checkpoint
from rvt2cli.eval.runner import EvalOptions, evaluate
from rvt2cli.tasks import get_task


class GpuMemory:
    """nvidia-smi every `every` seconds, in a thread: the peak of the memory in use (MiB) and of the processes
    listed as holding some."""

    def __init__(self, every: float = 0.5):
        self.every, self.peak_used, self.peak_processes, self.samples = every, 0, 0, 0
        self.idle = self._used()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)

    @staticmethod
    def _query(what: str) -> list[str]:
        try:
            out = subprocess.run(["nvidia-smi", f"--query-{what}", "--format=csv,noheader,nounits"],
                                 capture_output=True, text=True, timeout=10).stdout
        except (OSError, subprocess.TimeoutExpired):
            return []
        return [line for line in out.splitlines() if line.strip()]

    def _used(self) -> int:
        return sum(int(line.split(",")[0]) for line in self._query("gpu=memory.used"))

    def _watch(self) -> None:
        while not self._stop.wait(self.every):
            self.peak_used = max(self.peak_used, self._used())
            self.peak_processes = max(self.peak_processes, len(self._query("compute-apps=pid,used_memory")))
            self.samples += 1

    def __enter__(self) -> "GpuMemory":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def result(self) -> dict:
        return {"peak_mib_above_idle": max(0, self.peak_used - self.idle), "idle_mib": self.idle,
                "peak_processes_listed": self.peak_processes, "samples": self.samples}


def run(opts: EvalOptions) -> dict:
    with GpuMemory() as memory:
        start = time.perf_counter()
        result = evaluate(opts)
        seconds = time.perf_counter() - start
    outcomes = {(job.task, job.seed): (o.success, o.failure, [s.keyframe for s in o.steps]) for job, o in result.outcomes}
    keyframes = sum(len(o.steps) for _, o in result.outcomes)
    return {"seconds": seconds, "episodes": len(outcomes), "episodes_per_min": 60 * len(outcomes) / seconds,
            "keyframes": keyframes, "keyframes_per_s": keyframes / seconds,
            "successes": sum(o[0] for o in outcomes.values()), "gpu_memory": memory.result(), "_outcomes": outcomes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", help="a run or checkpoint")
    parser.add_argument("--random", metavar="CONFIG", help="instead: a checkpoint of this config with random weights")
    parser.add_argument("--tasks", default="push_cube,stack_cube")
    parser.add_argument("--episodes", type=int, default=4, help="per task")
    parser.add_argument("--seed", type=int, default=20_000, help="the first seed (default: the validation seeds')")
    parser.add_argument("--workers", type=int, default=14)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--keyframe-budget", type=int, default=25)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if bool(args.checkpoint) == bool(args.random):
        parser.error("give --checkpoint or --random CONFIG")
    tasks = tuple(args.tasks.split(","))
    with tempfile.TemporaryDirectory() as tmp:
        checkpoint = args.checkpoint or str(random_checkpoint(args.random, Path(tmp) / "run",
                                                              {t: list(get_task(t).scene_bounds) for t in tasks}))
        common = dict(checkpoint=checkpoint, tasks=tasks, episodes=args.episodes, seed=args.seed, workers=args.workers,
                      device=args.device, keyframe_budget=args.keyframe_budget)
        ways = {"policy_per_worker": {}, "shared_policy": {"shared_policy": True}}
        if args.device.startswith("cuda"):
            ways["cuda_graph_per_worker"] = {"cuda_graph": True}  # each worker's step replayed as a CUDA graph
        runs = {}
        for name, settings in ways.items():
            runs[name] = run(EvalOptions(**common, **settings, out=str(Path(tmp) / name)))
            r = runs[name]
            print(f"{name:>21}: {r['episodes']} episodes in {r['seconds']:.0f} s ({r['episodes_per_min']:.1f}/min, "
                  f"{r['keyframes_per_s']:.2f} keyframes/s), {r['successes']} successes, GPU memory at peak "
                  f"{r['gpu_memory']['peak_mib_above_idle']:,} MiB above idle, {r['gpu_memory']['peak_processes_listed']} "
                  "processes listed", flush=True)
    outcomes = {name: r.pop("_outcomes") for name, r in runs.items()}
    first = outcomes.pop("policy_per_worker")
    same = {name: sum(first[k] == other.get(k) for k in first) for name, other in outcomes.items()}
    for name, count in same.items():
        print(f"episodes that ended as with a policy per worker, {name}: {count} of {len(first)}")
    result = {"benchmark": "eval_share", "machine": describe(), "checkpoint": args.checkpoint or f"random {args.random}",
              "tasks": list(tasks), "episodes_per_task": args.episodes, "seed": args.seed, "workers": args.workers,
              "device": args.device, "keyframe_budget": args.keyframe_budget, "runs": runs, "same_outcomes": same, "episodes": len(first)}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
