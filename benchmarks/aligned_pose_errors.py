"""How far insert_peg's closed loop misses the aligned pose before the hole, and in which direction.

For every insert_peg episode of a policy's `rvt2 eval` journal, its keyframe K (default 2: the first after
the grasp) against the oracle's aligned pose on the same seed (the last keyframe before the oracle's
insertion, from an `rvt2 eval --oracle` journal) or, with `--insertion`, its keyframe K (then 3) against
the oracle's insertion (its last keyframe), both expressed in the frame of the box's hole (x along the
hole's axis, into the box; the seed's scene is reset to find it):

- axial: along the hole's axis (how far before the face);
- lateral: horizontal, across the axis;
- vertical;
- yaw: the turn about the vertical between the two poses.

    python -m benchmarks.aligned_pose_errors POLICY_EVAL_DIR ORACLE_EVAL_DIR [--keyframe 2] [--json out.json]
    python -m benchmarks.aligned_pose_errors POLICY_EVAL_DIR ORACLE_EVAL_DIR --insertion   # keyframe 3, the insertion
"""

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks.machine import describe
from rvt2cli.errors import UserError
from rvt2cli.eval.executor import rigid_transform
from rvt2cli.eval.journal import NAME, read_journal
from rvt2cli.tasks import get_task


def _by_seed(folder: str, source: str) -> dict[int, dict]:
    path = Path(folder) / NAME
    if not path.is_file():
        raise SystemExit(f"aligned_pose_errors: {path}: no evaluation journal; give `rvt2 eval --out` folders")
    try:
        _, records = read_journal(path)
    except UserError as error:
        raise SystemExit(f"aligned_pose_errors: {error}") from None
    return {r["seed"]: r for r in records if r["task"] == "insert_peg" and r["source"] == source}


def _first_tries(record: dict) -> list[dict]:
    """The episode's keyframes, without the executor's re-tries of the same one."""
    return [step for step in record["steps"] if step.get("retry", 0) == 0]


def _matrix(target) -> np.ndarray:
    """A journal's [x y z qx qy qz qw] -> 4x4."""
    return rigid_transform(target[:3], target[3:])


def hole_frame(env, seed: int) -> np.ndarray:
    from rvt2cli.record.scene import pose7

    env.reset(seed=seed)
    return _matrix(pose7(env.unwrapped.box_hole_pose))


def measure(policy_dir: str, oracle_dir: str, keyframe: int, insertion: bool = False) -> dict:
    from rvt2cli.record.scene import make_env

    policy, oracle = _by_seed(policy_dir, "policy"), _by_seed(oracle_dir, "oracle")
    env = make_env(get_task("insert_peg"), cameras=("front",), image_size=32)
    rows = []
    for seed in sorted(set(policy) & set(oracle)):
        steps, reference = _first_tries(policy[seed]), _first_tries(oracle[seed])
        if len(steps) <= keyframe or len(reference) < 2:
            continue
        hole = np.linalg.inv(hole_frame(env, seed))
        wanted = hole @ _matrix(reference[-1 if insertion else -2]["target"])
        predicted = hole @ _matrix(steps[keyframe]["target"])
        offset = (predicted[:3, 3] - wanted[:3, 3]) * 1000
        turn = Rotation.from_matrix(predicted[:3, :3] @ wanted[:3, :3].T)
        yaw = np.degrees(np.arctan2(*(turn.as_matrix()[[1, 0], 0])))   # about the hole frame's z (vertical)
        rows.append({"seed": seed, "axial_mm": offset[0], "lateral_mm": offset[1], "vertical_mm": offset[2],
                     "distance_mm": float(np.linalg.norm(offset)), "turn_deg": float(np.degrees(turn.magnitude())),
                     "yaw_deg": float(yaw)})
    env.close()
    if not rows:
        raise SystemExit("aligned_pose_errors: no insert_peg seed is in both journals")
    summary = {key: float(np.median(np.abs([r[key] for r in rows])))
               for key in ("axial_mm", "lateral_mm", "vertical_mm", "distance_mm", "turn_deg", "yaw_deg")}
    return {"episodes": len(rows), "median_abs": summary, "episodes_detail": rows}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policy", help="an `rvt2 eval --out` folder of a policy")
    p.add_argument("oracle", help="an `rvt2 eval --oracle --out` folder on the same seeds")
    p.add_argument("--keyframe", type=int, choices=range(0, 26), default=None, metavar="K",
                   help="the policy's keyframe to score, from 0 (default 2; with --insertion 3)")
    p.add_argument("--insertion", action="store_true", help="against the oracle's insertion instead of its aligned pose")
    p.add_argument("--json", help="write the result here too")
    args = p.parse_args(argv)
    keyframe = args.keyframe if args.keyframe is not None else (3 if args.insertion else 2)
    result = measure(args.policy, args.oracle, keyframe, args.insertion)
    m = result["median_abs"]
    wanted = "insertion" if args.insertion else "aligned pose"
    print(f"insert_peg, the policy's keyframe {keyframe} against the oracle's {wanted}, {result['episodes']} "
          f"episodes, median of absolute values: {m['distance_mm']:.0f} mm (axial {m['axial_mm']:.0f}, lateral "
          f"{m['lateral_mm']:.0f}, vertical {m['vertical_mm']:.0f}), turn {m['turn_deg']:.1f} deg "
          f"(yaw {m['yaw_deg']:.1f})")
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": describe(), "keyframe": keyframe, "against": wanted, **result}, indent=1))


if __name__ == "__main__":
    main()
