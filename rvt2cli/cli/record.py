"""`rvt2 record`: scripted-expert demonstrations in ManiSkill/SAPIEN -> MCAP episodes."""

import time

from rvt2cli.cli.args import COUNT, NON_NEGATIVE, POSITIVE, SEED, integer, names, task_expert


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "record", help="record expert demonstrations of a task into MCAP episode files",
        description="Run a task's scripted expert in the simulator (CPU) and write one MCAP file per successful "
                    "episode: dense robot and simulator state every control step, RGB-D images of the camera rig at "
                    "the frames training uses, and the keyframes and training samples (`rvt2 extract-keyframes`' rule). Seeds "
                    "run upwards from --seed; the same command writes the same files.",
    )
    p.add_argument("--task", type=names, help="task name, or several separated by commas (see --list-tasks)")
    p.add_argument("--task-set", help="record every task of this named set (e.g. rlbench18; see --list-tasks)")
    p.add_argument("--list-tasks", action="store_true", help="print the known tasks (variations, sets) and exit")
    p.add_argument("--variation", type=NON_NEGATIVE, help="record only this variation (default: the episodes spread "
                                                            "evenly over the task's variations, seed by seed)")
    p.add_argument("--hold-out-variations", action="store_true",
                   help="leave out the task's held_out_variations (a split for measuring generalisation)")
    p.add_argument("--episodes", type=COUNT, default=25, help="successful episodes to record, per task (default 25)")
    p.add_argument("--out", default="demos", help="output folder (default demos/)")
    p.add_argument("--seed", type=SEED, default=0, help="first seed (default 0)")
    p.add_argument("--workers", type=integer(1, 256), default=1, help="parallel simulator processes (default 1)")
    p.add_argument("--cameras", type=names, help="comma-separated camera names (default: the task's rig; "
                                     "'front' alone is the paper's single-camera setting)")
    p.add_argument("--image-size", type=integer(8, 2048), help="camera resolution (default: the task's, 128)")
    p.add_argument("--obs-every", type=COUNT, default=10, help="render the cameras every N frames besides keyframes (default 10)")
    p.add_argument("--voxel-size", type=POSITIVE, help="downsample fused clouds to this voxel size in metres (default: no)")
    p.add_argument("--store-clouds", action="store_true", help="also store the fused cloud (/points/world) for viewing in Foxglove")
    p.add_argument("--keep-failures", action="store_true", help="also keep episodes in which the expert failed")
    p.add_argument("--expert", action="append", default=[], type=task_expert, metavar="TASK=MODULE:FUNCTION",
                   help="record TASK with another scripted expert than its own (repeatable), e.g. "
                        "reach_and_drag=rvt2cli.record.rlbench18.reach_and_drag:expert_via_target")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--max-attempts", type=COUNT, help="give up after this many episodes (default 10 x --episodes + 10)")
    p.set_defaults(run=run)


def run(args) -> int:
    from rvt2cli.errors import UserError
    from rvt2cli.record.cameras import CAMERAS
    from rvt2cli.tasks import all_tasks, get_task, tasks_of_set

    if args.list_tasks:
        for task in all_tasks().values():
            sets = ",".join(task.task_sets) or "-"
            print(f"{task.name:<28} {task.env_id:<32} {task.num_variations:>3} variation{'s' if task.num_variations > 1 else ' '}"
                  f"  {sets:<12} {task.all_instructions()[0]!r}")
        return 0
    if bool(args.task) == bool(args.task_set):
        raise UserError("record needs --task NAME or --task-set SET, one of them (see `rvt2 record --list-tasks`)")
    if args.variation is not None and args.hold_out_variations:
        raise UserError("record takes --variation K or --hold-out-variations, not both")
    tasks = [get_task(n) for n in (args.task or tasks_of_set(args.task_set))]
    variations = "seen" if args.hold_out_variations else "all" if args.variation is None else str(args.variation)
    for task in tasks:
        task.variation_choices(variations)  # an unknown variation is one line, before any simulator starts
    cameras = args.cameras or None
    unknown = [c for c in cameras or () if c not in CAMERAS]
    if unknown:
        raise UserError(f"unknown camera(s) {', '.join(unknown)}; known cameras: {', '.join(CAMERAS)}")

    from rvt2cli.atomic import ensure_folder
    from rvt2cli.record.recorder import RecordOptions, check_experts

    check_experts(args.expert, [task.name for task in tasks])
    ensure_folder(args.out)  # before the progress bar: a bad --out is one line

    options = RecordOptions(cameras=cameras, image_size=args.image_size, obs_every=args.obs_every,
                            voxel_size=args.voxel_size, store_clouds=args.store_clouds, keep_failures=args.keep_failures,
                            variations=variations, experts=tuple(args.expert))
    return 0 if _record(tasks, args, options) else 1


def _record(tasks, args, options) -> bool:
    """Record every task's episodes (one pool of workers for all) with a progress bar, then a summary
    line per task; whether every task got its episodes."""
    from tqdm import tqdm

    from rvt2cli.record.recorder import record_tasks

    what = tasks[0].name if len(tasks) == 1 else f"{len(tasks)} tasks"
    bar = tqdm(total=args.episodes * len(tasks), unit="ep", desc=f"record {what}", dynamic_ncols=True,
               disable=args.no_progress)
    attempts = []

    def on_result(result, summary):
        attempts.append(result.success)
        if result.success:
            bar.update(1)
        if result.status == "error":
            tqdm.write(f"{summary.task} seed {result.seed}: simulator error, episode skipped: {result.error}")
        bar.set_postfix(attempts=len(attempts), expert_success=f"{sum(attempts) / len(attempts):.0%}")

    start = time.perf_counter()
    try:
        summaries = record_tasks([task.name for task in tasks], args.episodes, args.out, seed=args.seed,
                                 workers=args.workers, options=options, max_attempts=args.max_attempts,
                                 on_result=on_result)
    finally:
        bar.close()
    for task, summary in zip(tasks, summaries):
        _summarise(task, summary, args)
    if len(tasks) > 1:
        kept = sum(len(s.successes) for s in summaries)
        print(f"recorded {kept} episodes of {len(tasks)} tasks in {time.perf_counter() - start:.0f} s "
              f"with {args.workers} worker{'s' if args.workers > 1 else ''}")
    return all(summary.complete for summary in summaries)


def _summarise(task, summary, args) -> None:
    kept = [r for r in summary.results if r.path]
    mb = sum(r.size_bytes for r in kept) / max(1, len(kept)) / 1e6
    counts = ", ".join(f"{n} {status}" for status, n in sorted(summary.counts().items()))
    print(f"recorded {len(summary.successes)} successful {task.name} episodes into {args.out}/ ({mb:.1f} MB each, "
          f"done after {summary.seconds:.0f} s); expert success {summary.expert_success_rate:.0%} over "
          f"{len(summary.results)} attempts ({counts})")
    if task.num_variations > 1:
        spread = ", ".join(f"{v}: {n}" for v, n in summary.successes_per_variation().items())
        print(f"  episodes per variation: {spread}")
    if not summary.complete:
        print(f"rvt2: warning: only {len(summary.successes)} of {args.episodes} {task.name} episodes succeeded within "
              f"{len(summary.results)} attempts; raise --max-attempts to try more seeds")
