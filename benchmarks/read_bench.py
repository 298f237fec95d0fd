"""Reading recorded episodes: `rvt2 extract-keyframes` and the training data load, per file and in all.

    python -m benchmarks.read_bench DEMOS... [--workers N] [--json out.json]

DEMOS are episode files or folders (recorded by `rvt2 record`; copied first, since extraction rewrites
them). Times `extract_files` (what `rvt2 extract-keyframes` runs) and `load_samples` (what `rvt2 train`
reads episodes with) with one process, and with up to --workers processes where given (at most one per
runtime.FILES_PER_WORKER files, as the product decides; the table shows how many ran). Then `fit_clouds`,
which `rvt2 train`'s pack runs to put every cloud in a row of 50,000 points, in one thread and in --workers.
The loading process's own CPU time per file shows what it costs to receive the samples from the workers:
one process receives every file's, so on many cores it, not the workers, sets the pace of the load.
"""

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.machine import describe
from rvt2cli import runtime
from rvt2cli.data.paths import episode_paths
from rvt2cli.keyframes.extract import extract_files
from rvt2cli.train.options import TrainOptions
from rvt2cli.train.packed import fit_clouds
from rvt2cli.train.samples import load_samples

MAX_POINTS = TrainOptions.max_points  # rvt2 train's default


def measure(paths: list[Path], workers: int) -> dict:
    start = time.perf_counter()
    refused = [p for p, annotation in extract_files(paths, workers=workers) if isinstance(annotation, Exception)]
    extract = time.perf_counter() - start
    start, cpu = time.perf_counter(), time.process_time()
    samples = load_samples(paths, progress=False, workers=workers)
    load, receive = time.perf_counter() - start, time.process_time() - cpu   # this process's CPU, all its threads
    processes = runtime.file_workers(workers, len(paths))
    start = time.perf_counter()
    fit_clouds(samples, list(range(len(samples))), MAX_POINTS, np.random.default_rng(0), threads=workers)
    fit = time.perf_counter() - start
    return {"workers": workers, "processes": processes, "files": len(paths), "refused": len(refused), "extract_s": extract, "load_s": load,
            "extract_s_per_file": extract / len(paths), "load_s_per_file": load / len(paths),
            "reading_process_cpu_ms_per_file": 1e3 * receive / len(paths), "samples": len(samples),
            "points_per_sample": sum(len(x) for x in samples.xyz) / max(1, len(samples)),
            "fit_threads": workers, "fit_ms_per_sample": 1e3 * fit / max(1, len(samples))}


def compare_handovers(paths: list[Path], workers: int, rounds: int) -> list[dict]:
    """`load_samples` with the workers' clouds through files and through the result pipe, side by side, `rounds`
    times: wall seconds and the loading process's CPU per file; the samples must be the same."""
    runs, reference = [], None
    for round_ in range(rounds):
        for handover in ("files", "pipe"):
            start, cpu = time.perf_counter(), time.process_time()
            samples = load_samples(paths, progress=False, workers=workers, handover=handover)
            load, receive = time.perf_counter() - start, time.process_time() - cpu
            if reference is None:
                reference = samples
            elif not all(np.array_equal(a, b) for a, b in zip(reference.xyz + reference.rgb, samples.xyz + samples.rgb)):
                raise SystemExit(f"read_bench: the {handover} handover gave other clouds")
            runs.append({"round": round_, "handover": handover, "workers": workers, "files": len(paths), "load_s": load,
                         "reading_process_cpu_ms_per_file": 1e3 * receive / len(paths), "samples": len(samples)})
            print(f"round {round_}: {handover}: {load:.2f} s, the loading process's CPU {1e3 * receive / len(paths):.1f} ms a file")
    return runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("demos", nargs="+")
    parser.add_argument("--workers", type=int, default=1, help="also measure with this many processes")
    parser.add_argument("--handovers", type=int, metavar="ROUNDS", help="instead: the load alone with --workers, the "
                        "clouds handed over through files and through the pipe, side by side, ROUNDS times")
    parser.add_argument("--json")
    args = parser.parse_args()
    if args.handovers:
        paths = episode_paths(args.demos)
        runs = compare_handovers(paths, args.workers, args.handovers)
        if args.json:
            Path(args.json).write_text(json.dumps({"machine": describe(), "runs": runs}, indent=2))
        return
    with tempfile.TemporaryDirectory() as work:
        copies = []
        for path in episode_paths(args.demos):
            copies.append(Path(work) / path.name)
            shutil.copyfile(path, copies[-1])
        sizes = [p.stat().st_size for p in copies]
        runs = [measure(copies, w) for w in sorted({1, args.workers})]
    print(f"{len(copies)} episodes, {sum(sizes) / len(sizes) / 1e6:.2f} MB each")
    print("| processes | extract-keyframes, s per file | load for training, s per file | the loading process's CPU, ms per file "
          "| samples | points per sample | pack's rows, threads | ms per sample |")
    print("|---|---|---|---|---|---|---|---|")
    for r in runs:
        print(f"| {r['processes']} | {r['extract_s_per_file']:.3f} | {r['load_s_per_file']:.3f} | {r['reading_process_cpu_ms_per_file']:.1f} "
              f"| {r['samples']} | {r['points_per_sample']:.0f} | {r['fit_threads']} | {r['fit_ms_per_sample']:.2f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": describe(), "mb_per_file": sum(sizes) / len(sizes) / 1e6,
                                               "runs": runs}, indent=2))


if __name__ == "__main__":
    main()
