"""A checkpoint's rotation error on recorded demos, its scores decoded to the best bins' centres (as RVT
and PerAct decode) and refined by the neighbouring bins' scores (`rvt2cli.model.rotation.decode_euler`,
what rvt2 predicts with). The same observations, the same network: only the decoding differs.

    python -m benchmarks.rotation_decoding --checkpoint RUN --demos DEMOS... [--device cpu] [--json out.json]

Prints, per task and for the final keyframes (insertions, placements), the rotation error (median /
p90, degrees) both ways; positions are unchanged by the decoding.
"""

import argparse
import functools
import json
import tempfile

from benchmarks.machine import describe
from rvt2cli.eval.offline import evaluate_offline
from rvt2cli.model import policy as policy_module
from rvt2cli.model.rotation import decode_euler


def rotation_errors(report: dict) -> dict:
    rows = {}
    for task, scores in report["tasks"].items():
        rows[f"{task}, all"] = scores["rotation_deg"]
        for keyframe, per_keyframe in scores["keyframes"].items():
            rows[f"{task}, keyframe {keyframe}"] = per_keyframe["rotation_deg"]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--demos", nargs="+", required=True)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json")
    args = parser.parse_args()
    results = {}
    for name, refine in (("bin centres", False), ("refined", True)):
        policy_module.decode_euler = functools.partial(decode_euler, refine=refine)
        report = evaluate_offline(args.checkpoint, args.demos, out=tempfile.mkdtemp(prefix="rotation_decoding_"),
                                  device=args.device, progress=False)
        results[name] = rotation_errors(report)
    policy_module.decode_euler = decode_euler
    print("| task, keyframes | bin centres: deg median / p90 | refined: deg median / p90 |\n|---|---|---|")
    for row in results["refined"]:
        a, b = results["bin centres"][row], results["refined"][row]
        print(f"| {row} | {a['median']:.2f} / {a['p90']:.2f} | {b['median']:.2f} / {b['p90']:.2f} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": describe(), "checkpoint": args.checkpoint, "demos": args.demos, "rotation_deg": results}, f,
                      indent=2)


if __name__ == "__main__":
    main()
