"""The `rvt2` command line: argparse subcommands, each a thin shell over a library function.

Each module in `COMMAND_MODULES` registers its own subcommand through `register(subparsers)` and
imports its heavy dependencies (torch, the simulator) only when it runs, so `rvt2 --help` is quick.
"""

import importlib
import sys
import warnings

from rvt2cli import __version__
from rvt2cli.cli.args import Parser
from rvt2cli.errors import UserError

# In the order of the data flow; `rvt2 --help` lists them in this order.
COMMAND_MODULES = [
    "rvt2cli.cli.record",
    "rvt2cli.cli.import_rosbag",
    "rvt2cli.cli.info",
    "rvt2cli.cli.keyframes",
    "rvt2cli.cli.render",
    "rvt2cli.cli.pack_samples",
    "rvt2cli.cli.train",
    "rvt2cli.cli.eval",
    "rvt2cli.cli.diagnose",
    "rvt2cli.cli.export",
    "rvt2cli.cli.serve",
    "rvt2cli.cli.doctor",
]


def build_parser() -> Parser:
    parser = Parser(
        prog="rvt2",
        description="RVT-2 for ManiSkill/SAPIEN: record demos, extract keyframes, render views, train, evaluate, export.",
    )
    parser.add_argument("--version", action="version", version=f"rvt2 {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # Warnings for users (e.g. "task not in the checkpoint's training set") as one plain line.
    warnings.formatwarning = lambda message, *_, **__: f"rvt2: warning: {message}\n"
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args.run(args) or 0)
    except UserError as e:
        print(f"rvt2: error: {e}", file=sys.stderr)
        return e.exit_code
    except OSError as e:  # the environment refused a file operation that no check above anticipated
        where = f"{e.filename}: " if e.filename else ""
        print(f"rvt2: error: {where}{e.strerror or e}; check the path and its permissions", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("rvt2: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
