"""All speed benchmarks on the current machine: renderer, recording, training, the matrix products, inference and bag import.

    python -m benchmarks.run_all [--quick] [--out benchmarks/results/NAME]

Each benchmark writes its JSON into --out; this prints their tables and writes summary.md there.
--quick runs tiny configurations (CI: that they run, not how fast).
"""

import argparse
import subprocess
import sys
from pathlib import Path

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default="benchmarks/results/latest")
    parser.add_argument("--skip-record", action="store_true", help="no simulator (e.g. on a GPU machine without SAPIEN)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    quick = ["--quick"] if args.quick else []
    runs = [("render", ["benchmarks.render_bench", "--device", device]),
            ("policy", ["benchmarks.policy_bench", "--device", device]),
            ("gemm", ["benchmarks.gemm_bench", "--device", device]),
            ("rosbag", ["benchmarks.rosbag_bench"])]
    if not args.skip_record:
        runs.append(("record", ["benchmarks.record_bench"]))
    sections = []
    for name, command in runs:
        print(f"== {name}", flush=True)
        result = subprocess.run([sys.executable, "-m", *command, *quick, "--json", str(out / f"{name}.json")],
                                capture_output=True, text=True)
        print(result.stdout, end="")
        if result.returncode != 0:
            print(result.stderr, file=sys.stderr)
            sys.exit(f"benchmark {name} failed (exit code {result.returncode})")
        table = [line for line in result.stdout.splitlines() if line.startswith("|") or line.startswith("insert_peg") or " vs " in line]
        sections.append(f"## {name}\n\n" + "\n".join(table) + "\n")
    (out / "summary.md").write_text("# Benchmarks\n\n" + "\n".join(sections))
    print(f"results: {out}/")


if __name__ == "__main__":
    main()
