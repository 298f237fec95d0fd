"""`rvt2 pack-samples`: fuse the keyframe samples of episode files once into one file to train from elsewhere."""

from rvt2cli.cli.args import COUNT, names


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "pack-samples", help="pack annotated episodes' training samples into one file (train on a machine without the simulator)",
        description="Read annotated episodes (run `rvt2 extract-keyframes` first), fuse each sample's cloud, embed the "
                    "instructions, and write one .safetensors sample cache. `rvt2 train --data CACHE` then needs neither "
                    "the MCAP libraries nor the text encoder. Clouds are stored at 16 bits per axis within the scene bounds.",
    )
    p.add_argument("data", nargs="+", metavar="PATH", help="episode files or folders of them")
    p.add_argument("--out", required=True, help="the cache file to write (.safetensors)")
    p.add_argument("--episodes-per-task", type=COUNT, metavar="N", help="only each task's first N episodes (lowest seeds)")
    p.add_argument("--keyframe-starts-only", action="store_true",
                   help="only samples observed at frame 0 or at a keyframe (about a third of them; a smaller file)")
    p.add_argument("--include-failures", action="store_true", help="also episodes in which the expert failed")
    p.add_argument("--cameras", type=names, help="fuse only these cameras' points, e.g. front (the single-camera setting)")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(run=run)


def run(args) -> int:
    from rvt2cli.train.sample_cache import pack_sample_cache

    summary = pack_sample_cache(args.data, args.out, episodes_per_task=args.episodes_per_task,
                                keyframe_starts_only=args.keyframe_starts_only, include_failures=args.include_failures,
                                cameras=args.cameras,
                                progress=not args.no_progress)
    print(summary)
    return 0
