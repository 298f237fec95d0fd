"""`rvt2 extract-keyframes FILE...`: annotate episodes with keyframes and training samples."""

import sys

from rvt2cli.cli.args import COUNT, NON_NEGATIVE, POSITIVE, integer, number
from rvt2cli.errors import UserError


def register(subparsers) -> None:
    from rvt2cli.keyframes.rule import KeyframeParams

    d = KeyframeParams()
    p = subparsers.add_parser(
        "extract-keyframes", help="find keyframes (gripper change / arm at rest / last frame) and training samples",
        description="Find each episode's keyframes with the PerAct/RVT rule and write them, with the training samples "
                    "(observation frame -> next keyframe), into the episode file (atomically; re-running replaces them).",
    )
    p.add_argument("files", nargs="+", metavar="FILE", help="episode .mcap files or folders of them")
    p.add_argument("--dry-run", action="store_true", help="only report; write nothing")
    p.add_argument("--stop-velocity", type=POSITIVE, default=d.stop_velocity,
                   help=f"rad/s: the arm has stopped where every arm joint becomes slower than this (default {d.stop_velocity}; "
                        "PerAct/RVT use 0.1 on RLBench, which fires a step or three early at ManiSkill's 20 Hz)")
    p.add_argument("--pause-velocity", type=POSITIVE, default=d.pause_velocity,
                   help=f"rad/s: a stretch slower than this between two motions that never gets slower than --stop-velocity "
                        f"is a keyframe at its slowest frame (default {d.pause_velocity})")
    p.add_argument("--stop-buffer", type=NON_NEGATIVE, default=d.stop_buffer,
                   help=f"frames a rest keyframe blocks the next one (default {d.stop_buffer}, as the reference)")
    p.add_argument("--obs-every", type=COUNT, default=d.obs_every,
                   help=f"an observation start every N frames besides the keyframes (default {d.obs_every}, as the reference)")
    p.add_argument("--merge-refinements", type=number(0.0), default=d.merge_m * 1000, metavar="MM",
                   help="drop each rest keyframe that the next rest keyframe moves by less than MM millimetres and turns "
                        f"by less than {d.merge_deg:g} degrees: an expert's re-aiming in small steps becomes one keyframe "
                        "(default 0: keep them)")
    p.add_argument("--workers", type=integer(1, 256), default=None,
                   help="processes reading and writing the files (default: one per usable core, at most one per 32 files)")
    p.set_defaults(run=run)


def run(args) -> int:
    from rvt2cli.data.paths import episode_paths
    from rvt2cli.keyframes.extract import describe, extract_files
    from rvt2cli.keyframes.rule import KeyframeParams
    from rvt2cli.runtime import usable_cores

    params = KeyframeParams(stop_velocity=args.stop_velocity, pause_velocity=args.pause_velocity, stop_buffer=args.stop_buffer,
                            obs_every=args.obs_every, merge_m=args.merge_refinements / 1000)
    failed = []
    paths = episode_paths(args.files)
    for path, annotation in extract_files(paths, params, args.dry_run, args.workers or usable_cores()):
        if isinstance(annotation, UserError):
            print(f"rvt2: error: {annotation}", file=sys.stderr)
            failed.append(path.name)
            continue
        print(f"{path}: {describe(annotation)}")
    done = len(paths) - len(failed)
    verb = "checked" if args.dry_run else "annotated"
    print(f"{done} of {len(paths)} files {verb}" + (f"; failed: {', '.join(failed)}" if failed else ""))
    return 2 if failed else 0
