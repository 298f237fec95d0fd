"""`rvt2 train`: train an RVT-2 policy on annotated episodes (also under torchrun for several GPUs)."""


def register(subparsers) -> None:
    from rvt2cli.train.trainer import TrainOptions as T

    p = subparsers.add_parser(
        "train", help="train a multi-task, language-conditioned RVT-2 policy on keyframe samples",
        description="Train RVT-2 on the keyframe samples of episode files (run `rvt2 extract-keyframes` first). "
                    "Several GPUs: torchrun --nproc-per-node N -m rvt2cli train ...",
    )
    p.add_argument("--data", nargs="+", required=True, metavar="PATH",
                   help="episode files or folders of them, or one sample cache written by `rvt2 pack-samples`")
    p.add_argument("--out", required=True, help="run folder (checkpoints, train.csv, tb/)")
    p.add_argument("--config", default=T.config, help="model config: rvt2 (the paper), small (CPU), rvt (RVT-1-like ablation)")
    p.add_argument("--steps", type=int, default=T.steps, help=f"optimizer steps (default {T.steps})")
    p.add_argument("--batch-size", type=int, default=T.batch_size, help=f"per device (default {T.batch_size}, as the paper)")
    p.add_argument("--lr", type=float, help="peak learning rate (default 1.25e-5 x total batch, as the paper)")
    p.add_argument("--warmup", type=int, default=T.warmup, help=f"warmup steps, at most a tenth of --steps (default {T.warmup})")
    p.add_argument("--max-points", type=int, default=T.max_points, help=f"points per cloud, subsampled/padded (default {T.max_points})")
    p.add_argument("--no-augment", action="store_true", help="no translation/yaw augmentation (e.g. to overfit a tiny set)")
    p.add_argument("--seed", type=int, default=T.seed)
    p.add_argument("--device", default=T.device, help="auto (default), cpu, cuda, cuda:N")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--save-every", type=int, default=T.save_every)
    p.add_argument("--val-every", type=int, default=T.val_every)
    p.add_argument("--val-episodes", type=int, default=T.val_episodes, help="episodes held out per task for validation")
    p.add_argument("--include-failures", action="store_true", help="also train on episodes in which the expert failed")
    p.add_argument("--episodes-per-task", type=int, metavar="N",
                   help="train on each task's first N episodes only (lowest seeds), e.g. 10 for the few-demo setting")
    p.add_argument("--keyframe-starts-only", action="store_true",
                   help="only samples observed at frame 0 or at a keyframe, not those every --obs-every frames in between")
    p.add_argument("--no-amp", action="store_true", help="no bf16 autocast on CUDA")
    p.add_argument("--compile", action="store_true", help="torch.compile the network (GPU: ~1.5x faster after a minute of compiling)")
    p.add_argument("--no-8bit", action="store_true", help="plain LAMB even when bitsandbytes is installed")
    p.add_argument("--render-backend", default=T.render_backend, choices=["warp", "torch"])
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(run=run)


def run(args) -> int:
    from rvt2cli.train.trainer import TrainOptions, train

    opts = TrainOptions(data=args.data, out=args.out, config=args.config, steps=args.steps, batch_size=args.batch_size,
                        lr=args.lr, warmup=args.warmup, max_points=args.max_points, augment=not args.no_augment, seed=args.seed, device=args.device,
                        resume=args.resume, save_every=args.save_every, val_every=args.val_every,
                        val_episodes=args.val_episodes, include_failures=args.include_failures,
                        episodes_per_task=args.episodes_per_task, keyframe_starts_only=args.keyframe_starts_only, amp=not args.no_amp, compile=args.compile,
                        eight_bit=not args.no_8bit, render_backend=args.render_backend, progress=not args.no_progress)
    result = train(opts)
    v = result.last_validation
    print(f"trained {result.steps} steps in {result.seconds:.0f} s; checkpoint: {result.run_dir}/last"
          + (f"; validation: {v['translation_mm']:.1f} mm, {v['rotation_deg']:.1f} deg, gripper {v['gripper_accuracy']:.0%}" if v else "")
          + (f"; {result.skipped_steps} non-finite steps skipped" if result.skipped_steps else ""))
    return 0
