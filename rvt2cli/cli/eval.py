"""`rvt2 eval`: closed-loop success in the simulator, with the executor's ceiling (--oracle)."""


def register(subparsers) -> None:
    from rvt2cli.eval.options import EvalOptions as E

    p = subparsers.add_parser(
        "eval", help="evaluate a checkpoint closed-loop in the simulator (success per task, videos, report)",
        description="Run episodes on seeds the demos did not use: observe, predict the next keyframe, execute it "
                    "with the mplib motion planner, until the task's success check passes or a budget runs out. "
                    "--oracle runs the same executor on ground-truth keyframes: the ceiling of any keyframe policy.",
    )
    p.add_argument("--checkpoint", help="run folder or checkpoint written by `rvt2 train`")
    p.add_argument("--tasks", help="comma-separated (default: the checkpoint's training tasks)")
    p.add_argument("--episodes", type=int, default=E.episodes, help=f"per task (default {E.episodes})")
    p.add_argument("--seed", type=int, default=E.seed, help=f"first seed (default {E.seed}; demos use 0 upwards)")
    p.add_argument("--workers", type=int, default=E.workers,
                   help="parallel simulator processes, one core each")
    p.add_argument("--oracle", action="store_true", help="also run the executor on ground-truth keyframes")
    p.add_argument("--demos", nargs="+", metavar="PATH", help="with --oracle: use these recorded demos' keyframes (and seeds)")
    p.add_argument("--instruction", help="evaluate with this phrasing of the instruction instead of the task's")
    p.add_argument("--video", action="store_true", help="write an mp4 per episode (slow on CPU rendering)")
    p.add_argument("--save-rollouts", action="store_true", help="write each rollout's predictions as MCAP")
    p.add_argument("--keyframe-budget", type=int, default=E.keyframe_budget)
    p.add_argument("--out", help="output folder (default: CHECKPOINT/eval)")
    p.add_argument("--device", default=E.device, help="policy device (default cpu)")
    p.set_defaults(run=run)


def run(args) -> int:
    import warnings

    from tqdm import tqdm

    from rvt2cli.eval.runner import EvalOptions, evaluate

    warnings.simplefilter("default")
    opts = EvalOptions(checkpoint=args.checkpoint, tasks=tuple(t for t in (args.tasks or "").split(",") if t),
                       episodes=args.episodes, seed=args.seed, workers=args.workers, oracle=args.oracle,
                       demos=tuple(args.demos or ()), instruction=args.instruction, video=args.video,
                       save_rollouts=args.save_rollouts, keyframe_budget=args.keyframe_budget, out=args.out, device=args.device)
    bars = []

    def on_start(total):
        bars.append(tqdm(total=total, desc="eval", unit="ep", dynamic_ncols=True))

    def on_outcome(job, outcome, finished):
        bar = bars[0]
        bar.update(1)
        rates = {}
        for j, o in finished:
            rates.setdefault(j.source, []).append(o.success)
        bar.set_postfix({s: f"{sum(v) / len(v):.0%}" for s, v in rates.items()})
        if outcome.error:
            tqdm.write(f"{job.task} seed {job.seed}: simulator error, episode counted as failed: {outcome.error}")

    try:
        result = evaluate(opts, on_outcome, on_start)
    finally:
        for bar in bars:
            bar.close()
    for task, per in result.report["tasks"].items():
        print(f"{task:<18} " + "  ".join(f"{s} {r['success_rate']:.0%} ({r['successes']}/{r['episodes']})" for s, r in per.items()))
    print(f"report: {result.out_dir}/eval.md, eval.json, eval.png")
    return 0
