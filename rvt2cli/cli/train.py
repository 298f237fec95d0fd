"""`rvt2 train`: train an RVT-2 policy on annotated episodes (also under torchrun for several GPUs)."""

import argparse
import os

from rvt2cli.cli.args import COUNT, NON_NEGATIVE, POSITIVE, SEED, integer, names, number, weights


OUT_OF_TIME = 75   # sysexits' EX_TEMPFAIL: stopped at --time-limit, not finished; run again with --resume


def exit_code(out_of_time: bool) -> int:
    """75 for a run stopped at --time-limit; 0 under torchrun, whose agent reports any other code as a failed
    worker (run.json's `out_of_time` says it there)."""
    return OUT_OF_TIME if out_of_time and "LOCAL_RANK" not in os.environ else 0


def register(subparsers) -> None:
    from rvt2cli.train.options import TrainOptions as T

    p = subparsers.add_parser(
        "train", help="train a multi-task, language-conditioned RVT-2 policy on keyframe samples",
        description="Train RVT-2 on the keyframe samples of episode files (run `rvt2 extract-keyframes` first). "
                    "Several GPUs: torchrun --nproc-per-node N -m rvt2cli train ... "
                    "--resume continues the run in --out with the options it was started with.",
        argument_default=argparse.SUPPRESS,  # only the flags given: a resumed run takes the rest from the run
    )
    p.add_argument("--data", nargs="+", metavar="PATH",
                   help="episode files or folders of them, or one sample cache written by `rvt2 pack-samples`")
    p.add_argument("--out", required=True, help="run folder (checkpoints, train.csv, validation.csv, tb/)")
    p.add_argument("--config", help="model config: rvt2 (the paper, default), small (CPU), rvt (RVT-1-like ablation)")
    p.add_argument("--rotation-bins", type=integer(4, 720), metavar="N",
                   help="Euler-angle bins per axis (default: the config's 72, i.e. 5 degrees, as the paper; "
                        "360 gives 1 degree, which a 3 mm insertion needs: rvt2 diagnose precision-budget)")
    p.add_argument("--rotation-sigma", type=number(0.0, 45.0), metavar="DEG",
                   help="train rotations against a Gaussian of DEG degrees around the true angle instead of its one "
                        "bin (default 0: one bin, as the paper); fine bins learn from their neighbours, and the "
                        "prediction decodes between bin centres (e.g. --rotation-bins 360 --rotation-sigma 2)")
    p.add_argument("--zoom", type=number(1.0, 16.0), metavar="Z",
                   help="two-stage configs: stage 2 sees 1/Z of the workspace around its centre (default 4, as the "
                        "paper: +-10 cm of the default 0.8 m workspace); 2 sees +-20 cm at half the resolution")
    p.add_argument("--stage2-min-points", type=NON_NEGATIVE, metavar="N",
                   help="two-stage configs, at inference: keep stage 1's point where fewer than N cloud points lie in "
                        "stage 2's zoomed box (it saw nothing to place the keyframe by); stored in the checkpoint, "
                        "`rvt2 eval --stage2-min-points` overrides it (default 200; 0: always stage 2's, as the paper)")
    p.add_argument("--coarse-action-features", action="store_true",
                   help="two-stage configs: the rotation, gripper and collision heads also read stage 1's features, "
                        "which see the whole workspace, not only stage 2's box (for targets far from what defines "
                        "them, such as insert_peg's aligned pose before the box; default: stage 2's alone, as the paper)")
    p.add_argument("--aim-held", action="store_true",
                   help="once the gripper closes, the position heads aim the task's aim_offset (tasks/*.toml: "
                        "insert_peg's lies 12 cm along the held peg) instead of the TCP, so stage 2 zooms in on the "
                        "hole the peg goes to, not on free space behind it; the prediction is still the TCP's "
                        "(default: the TCP throughout, as the paper)")
    p.add_argument("--steps", type=COUNT, help=f"optimizer steps (default {T.steps})")
    p.add_argument("--batch-size", type=COUNT, help=f"per device (default {T.batch_size}, as the paper)")
    p.add_argument("--micro-batch", type=COUNT, metavar="M",
                   help="run each batch M samples at a time, the gradients summed to the batch's (the same step with "
                        "less GPU memory; --batch-size must be a multiple of M)")
    p.add_argument("--lr", type=POSITIVE, help="peak learning rate (default 1.25e-5 x total batch, as the paper)")
    p.add_argument("--warmup", type=NON_NEGATIVE, help=f"warmup steps, at most a tenth of --steps (default {T.warmup})")
    p.add_argument("--max-points", type=integer(16), help=f"points per cloud, subsampled/padded (default {T.max_points})")
    p.add_argument("--no-augment", dest="augment", action="store_false", help="no translation/yaw augmentation (e.g. to overfit a tiny set)")
    p.add_argument("--seed", type=SEED, help=f"(default {T.seed})")
    p.add_argument("--device", help="auto (default), cpu, cuda, cuda:N")
    p.add_argument("--samples-on", choices=["auto", "host", "device"],
                   help="where the packed clouds live: host (each batch's rows copied to the GPU beside the step), "
                        "device, or auto (default: the GPU where they take at most half its free memory)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint, with its options")
    p.add_argument("--time-limit", type=POSITIVE, metavar="MINUTES",
                   help="save a checkpoint and stop once this many minutes have passed since the command started "
                        "(a cluster job's or a rented machine's time; leave a minute for the save); exit code 75 (0 "
                        "under torchrun, with out_of_time in run.json), and --resume continues exactly where it stopped")
    p.add_argument("--save-every", type=COUNT, help=f"steps between checkpoints (default {T.save_every})")
    p.add_argument("--val-every", type=COUNT, help=f"steps between validations (default {T.val_every})")
    p.add_argument("--log-every", type=COUNT, help=f"steps between log rows (default {T.log_every})")
    p.add_argument("--val-episodes", type=NON_NEGATIVE, help=f"episodes held out per task for validation (default {T.val_episodes})")
    p.add_argument("--include-failures", action="store_true", help="also train on episodes in which the expert failed")
    p.add_argument("--task-set", metavar="SET",
                   help="train only on the episodes of this named set's tasks in --data (e.g. rlbench18; see rvt2 record --list-tasks)")
    p.add_argument("--episodes-per-task", type=COUNT, metavar="N",
                   help="train on each task's first N episodes only (lowest seeds), e.g. 10 for the few-demo setting")
    p.add_argument("--keyframe-starts-only", action="store_true",
                   help="only samples observed at frame 0 or at a keyframe, not those every --obs-every frames in between")
    p.add_argument("--start-share", type=number(0.0, 1.0), metavar="P",
                   help="draw this share of each task's samples from those observed at frame 0 or at a keyframe, "
                        "the only observations a closed loop makes (default 0: every sample alike, as the paper); "
                        "e.g. 0.5")
    p.add_argument("--task-weights", type=weights, metavar="TASK=W,...",
                   help="draw tasks in proportion to these weights (tasks left out: 1) instead of uniformly, e.g. "
                        "insert_peg=3,plug_charger=3 to give the insertions more of the training (default: every task alike, as the paper)")
    p.add_argument("--phrasings", choices=["demo", "all", "first"],
                   help="demo: each sample keeps its demo's instruction, one of its variation's trained phrasings drawn "
                        "by the demo's seed (default); all: each draw takes one of the trained phrasings (tasks/*.toml's "
                        "instructions) of its variation, so every variation is seen in every phrasing; first: each sample "
                        "reads its variation's first phrasing, RLBench's descriptions[0], as the paper trains (evaluate "
                        "with rvt2 eval --first-phrasing)")
    p.add_argument("--cameras", type=names, help="fuse only these cameras' points, e.g. front (the single-camera setting)")
    p.add_argument("--no-amp", dest="amp", action="store_false", help="no bf16 autocast on CUDA")
    p.add_argument("--compile", action="store_true", help="torch.compile the network (GPU: ~1.5x faster after a minute of compiling)")
    p.add_argument("--no-8bit", dest="eight_bit", action="store_false", help="32-bit LAMB states on CUDA too")
    p.add_argument("--render-backend", choices=["warp", "torch"])
    p.add_argument("--no-progress", dest="progress", action="store_false")
    p.set_defaults(run=run)


def options_from(args) -> "TrainOptions":  # noqa: F821 - imported lazily
    """The run's options: the flags given, over the stored options of a resumed run or the defaults."""
    from dataclasses import fields
    from pathlib import Path

    from rvt2cli.errors import UserError
    from rvt2cli.train.options import TrainOptions

    given = {f.name: getattr(args, f.name) for f in fields(TrainOptions) if hasattr(args, f.name)}
    if given.get("resume"):
        from rvt2cli.train.run_folder import stored_options

        stored = stored_options(Path(args.out))
        if stored is not None:  # a time limit belongs to the command that gave it, not to the run
            return TrainOptions(**{**stored.__dict__, "time_limit": None, **given})
    if "data" not in given:
        raise UserError("train needs --data (episode files or folders, or a sample cache)")
    return TrainOptions(**given)


def run(args) -> int:
    from rvt2cli.train.trainer import describe_terms, train

    result = train(options_from(args))
    if int(os.environ.get("RANK", "0")) != 0:  # one summary for a several-GPU run, from the process that saves
        return exit_code(result.out_of_time)
    v = result.last_validation
    print(f"trained {result.steps} steps in {result.seconds:.0f} s; checkpoint: {result.run_dir}/last"
          + (f"; validation: stage-2 error {v['translation_mm_median']:.1f} mm median, {v['rotation_deg_median']:.1f} deg, "
             f"gripper {v['gripper_accuracy']:.0%}" if v else "")
          + (f"; {result.skipped_steps} non-finite steps skipped" if result.skipped_steps else "")
          # the terms of this call's skipped steps (a resumed run's count includes the steps before it)
          + (f" (not finite: {describe_terms(result.skipped_terms)})" if result.skipped_terms else ""))
    return exit_code(result.out_of_time)
