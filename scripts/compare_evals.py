"""Do two `rvt2 eval` runs agree episode by episode? Compares the episodes the second run holds with the
same (source, task, seed) of the first: outcome, keyframes, control steps, and every keyframe's target
and error at rest.

    python scripts/compare_evals.py EVAL_DIR_A EVAL_DIR_B
"""

import sys
from pathlib import Path

from rvt2cli.errors import UserError
from rvt2cli.eval.journal import NAME, episode_key, read_journal


def episodes(folder: str) -> dict:
    path = Path(folder) / NAME
    if not path.exists():
        sys.exit(f"{path}: no evaluation journal here; give two `rvt2 eval --out` folders")
    try:
        _, records = read_journal(path)
    except UserError as error:
        sys.exit(str(error))
    return {episode_key(r): r for r in records}


def main() -> None:
    if len(sys.argv) != 3:
        sys.exit(__doc__.strip().splitlines()[-1].strip())
    first, second = episodes(sys.argv[1]), episodes(sys.argv[2])
    shared = sorted(k for k in second if k in first)
    same_outcome = sum(first[k]["success"] == second[k]["success"] for k in shared)
    identical = [k for k in shared if first[k]["steps"] == second[k]["steps"] and first[k]["success"] == second[k]["success"]
                 and first[k]["control_steps"] == second[k]["control_steps"]]
    print(f"{len(shared)} episodes in both: {same_outcome} with the same outcome, {len(identical)} identical in every "
          f"keyframe (targets, errors at rest, control steps)")
    for k in shared:
        if k not in identical:
            a, b = first[k], second[k]
            print(f"  differs: {k[1]} seed {k[2]} ({k[0]}): success {a['success']} / {b['success']}, "
                  f"keyframes {a['keyframes']} / {b['keyframes']}, control steps {a['control_steps']} / {b['control_steps']}")


if __name__ == "__main__":
    main()
