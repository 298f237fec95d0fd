"""`rvt2 info FILE...`: what is in episode files."""

import json
import sys

from rvt2cli.errors import UserError


def register(subparsers) -> None:
    p = subparsers.add_parser("info", help="summarise episode files (task, frames, cameras, keyframes, channels)",
                              description="Summarise rvt2 episode files.")
    p.add_argument("files", nargs="+", metavar="FILE", help="episode .mcap files")
    p.add_argument("--json", action="store_true", help="print one JSON list for machines")
    p.set_defaults(run=run)


def run(args) -> int:
    from rvt2cli.data.summary import format_summary, summarize

    summaries, failed = [], 0
    for path in args.files:
        try:
            summaries.append(summarize(path))
        except UserError as e:
            print(f"rvt2: error: {e}", file=sys.stderr)
            failed += 1
            continue
        if not args.json:
            print(format_summary(summaries[-1]))
    if args.json:
        print(json.dumps(summaries, indent=2))
    return 2 if failed else 0
