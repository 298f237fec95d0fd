"""`rvt2 eval`: closed-loop success in the simulator, with the executor's ceiling (--oracle); or, with
--offline, the policy's precision on recorded demos without a simulator."""

from rvt2cli.cli.args import COUNT, NON_NEGATIVE, SEED, integer, names, number


def register(subparsers) -> None:
    from rvt2cli.eval.options import EvalOptions as E

    p = subparsers.add_parser(
        "eval", help="evaluate a checkpoint closed-loop in the simulator (success per task, videos, report), or offline on demos",
        description="Run episodes on seeds the demos did not use: observe, predict the next keyframe, execute it "
                    "with the mplib motion planner and a joint servo, until the task's success check passes or a budget "
                    "runs out. --oracle runs the same executor on ground-truth keyframes: the ceiling of a keyframe policy. "
                    "--offline DEMOS scores the policy's predictions on recorded demos in millimetres, without a simulator.",
    )
    p.add_argument("--checkpoint", help="run folder or checkpoint written by `rvt2 train`")
    p.add_argument("--policy-url", metavar="URL",
                   help="instead of --checkpoint: a policy served by `rvt2 serve` (ws://HOST:PORT), called as a robot calls it")
    p.add_argument("--token-file", metavar="FILE", help="with --policy-url: the file holding the server's shared secret")
    p.add_argument("--offline", nargs="+", metavar="DEMOS", help="score the checkpoint on these recorded episodes (files or folders)")
    p.add_argument("--tasks", type=names, help="comma-separated (default: the checkpoint's training tasks)")
    p.add_argument("--task-set", help="evaluate every task of this named set (e.g. rlbench18; see rvt2 record --list-tasks)")
    p.add_argument("--variations", default=E.variations, metavar="WHICH",
                   help="the variations episodes spread over, seed by seed: all (default), held-out (each task's "
                        "held_out_variations; tasks without them are left out), seen (all but those) or one index K")
    p.add_argument("--paraphrases", action="store_true",
                   help="instruct with each task's held-out paraphrases (tasks/*.toml) instead of its training instructions")
    p.add_argument("--first-phrasing", action="store_true",
                   help="instruct every episode with its variation's first trained phrasing, RLBench's first description, "
                        "as PerAct, RVT and RVT-2 evaluate (default: one of the trained phrasings, drawn by the seed)")
    p.add_argument("--episodes", type=COUNT, default=E.episodes, help=f"per task (default {E.episodes})")
    p.add_argument("--seed", type=SEED, default=E.seed, help=f"first seed (default {E.seed}; demos use 0 upwards)")
    p.add_argument("--workers", type=integer(1, 256), default=E.workers, help="parallel simulator processes, one core each")
    p.add_argument("--shared-policy", action="store_true",
                   help="with --workers N: load the checkpoint once, in this process (on --device), and let the N simulator "
                        "processes ask it for keyframes over the loopback, batched, every forward pass at N requests (padded) so "
                        "that an episode does not depend on which others asked with it (docs/SERVING.md); default: each "
                        "worker loads its own copy")
    p.add_argument("--cuda-graph", action="store_true",
                   help="with --device cuda: each worker replays its policy step as one CUDA graph (captured at its first "
                        "keyframe), the same keyframes as the eager step without its launch gaps")
    p.add_argument("--oracle", action="store_true", help="also run the executor on ground-truth keyframes")
    p.add_argument("--demos", nargs="+", metavar="PATH", help="with --oracle: use these recorded demos' keyframes (and seeds)")
    p.add_argument("--instruction", help="evaluate with this phrasing of the instruction instead of the task's")
    p.add_argument("--video", action="store_true", help="write an mp4 per episode (slow on CPU rendering)")
    p.add_argument("--save-rollouts", action="store_true", help="write each rollout's predictions as MCAP")
    p.add_argument("--keyframe-budget", type=COUNT, default=E.keyframe_budget, help=f"keyframes per episode (default {E.keyframe_budget})")
    p.add_argument("--max-replans", type=NON_NEGATIVE, default=E.max_replans,
                   help=f"re-predictions after an unreachable keyframe, in a row (default {E.max_replans})")
    p.add_argument("--step-budget-scale", type=number(0.0, 100.0, exclusive_minimum=True), default=E.step_budget_scale,
                   help=f"control steps per episode: this x the task's max_steps (default {E.step_budget_scale:g}; the "
                        "keyframe budget is the measure, this only ends episodes that keep the arm busy)")
    p.add_argument("--no-insertion-search", dest="insertion_search", action="store_false",
                   help="push insertions straight to the keyframe, as RLBench's executor does, instead of searching for "
                        "the hole where the held object stops at a face (tasks with search_pitch_mm)")
    p.add_argument("--resume", action="store_true", help="continue the evaluation in --out (after a crash or Ctrl-C)")
    p.add_argument("--replay", metavar="JOURNAL",
                   help="instead of a checkpoint: the keyframes a policy predicted in a recorded evaluation (its "
                        "episodes.jsonl), run through this executor (its seeds within --seed and --episodes)")
    p.add_argument("--stage2-min-points", type=NON_NEGATIVE, metavar="N",
                   help="keep stage 1's point where fewer than N cloud points lie in stage 2's zoomed box (it saw nothing "
                        "to place the keyframe by; default: the checkpoint's, 200 for models trained with the default since it "
                        "became one, 0 for those trained before)")
    p.add_argument("--batch-size", type=COUNT, default=8, help="--offline: observations per forward pass (default 8)")
    p.add_argument("--out", help="output folder (default: CHECKPOINT/eval, or CHECKPOINT/offline)")
    p.add_argument("--device", default=E.device, help="policy device (default cpu)")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(run=run)


def run(args) -> int:
    if args.offline:
        return run_offline(args)
    import warnings

    from tqdm import tqdm

    from rvt2cli.eval.runner import EvalOptions, evaluate

    from rvt2cli.errors import UserError
    from rvt2cli.tasks import tasks_of_set

    warnings.simplefilter("default")
    if args.tasks and args.task_set:
        raise UserError("eval takes --tasks or --task-set, not both")
    chosen = _word_options(args)
    if len(chosen) > 1:
        raise UserError(f"eval takes one of --paraphrases, --first-phrasing and --instruction; {' and '.join(chosen)} were given")
    tasks = tuple(tasks_of_set(args.task_set)) if args.task_set else args.tasks or ()
    if args.token_file and not args.policy_url:
        raise UserError("--token-file goes with --policy-url (the served policy's shared secret)")
    token = None
    if args.token_file:
        from rvt2cli.serve.options import token_from_file

        token = token_from_file(args.token_file)
    opts = EvalOptions(checkpoint=args.checkpoint, tasks=tasks, paraphrases=args.paraphrases, first_phrasing=args.first_phrasing, variations=args.variations, episodes=args.episodes, seed=args.seed,
                       workers=args.workers, oracle=args.oracle, demos=tuple(args.demos or ()), instruction=args.instruction,
                       video=args.video, save_rollouts=args.save_rollouts, keyframe_budget=args.keyframe_budget,
                       max_replans=args.max_replans, step_budget_scale=args.step_budget_scale, out=args.out,
                       device=args.device, resume=args.resume, replay=args.replay, insertion_search=args.insertion_search,
                       stage2_min_points=args.stage2_min_points, policy_url=args.policy_url, token=token,
                       shared_policy=args.shared_policy, cuda_graph=args.cuda_graph)
    bars = []

    def on_start(total):
        bars.append(tqdm(total=total, desc="eval", unit="ep", dynamic_ncols=True, disable=args.no_progress))

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
        print(f"{task:<28} " + "  ".join(
            f"{s} {r['success_rate']:.0%} ({r['successes']}/{r['episodes']}, error at rest "
            + (f"{r['pose_error']['position_mm']['median']:.2f} mm median, {r['pose_error']['position_mm']['p95']:.2f} p95)"
               if r['pose_error']['keyframes'] else "-)")
            for s, r in per.items()))
        for s, r in per.items():
            if len(r["variations"]) > 1:
                print(f"  {s} per variation: " + ", ".join(f"{v}: {x['successes']}/{x['episodes']}"
                                                         for v, x in r["variations"].items()))
    print(f"report: {result.out_dir}/eval.md, eval.json, eval.png")
    return 0


def _word_options(args) -> list[str]:
    """The options given that choose a closed-loop episode's words (EvalOptions.instruction_for)."""
    return [flag for flag, given in (("--paraphrases", args.paraphrases), ("--first-phrasing", args.first_phrasing),
                                     ("--instruction", args.instruction)) if given]


def run_offline(args) -> int:
    from pathlib import Path

    from rvt2cli.errors import UserError
    from rvt2cli.eval.offline import evaluate_offline, headline_line

    if not args.checkpoint or args.policy_url:
        raise UserError("eval --offline needs --checkpoint (it scores a checkpoint loaded here, not a served policy)")
    words = _word_options(args)
    if words:
        raise UserError(f"eval --offline scores each demo under the words its checkpoint was trained to read; {words[0]} "
                        "chooses a closed-loop episode's words: leave it out")
    out = args.out or str(Path(args.checkpoint) / "offline")
    report = evaluate_offline(args.checkpoint, args.offline, out, device=args.device, batch_size=args.batch_size,
                              progress=not args.no_progress, stage2_min_points=args.stage2_min_points)
    print(headline_line(report))
    print(f"report: {out}/offline.md, offline.json")
    return 0
