"""`rvt2 diagnose NAME`: why a policy fails, one question per NAME (the analyses of `rvt2cli.diagnose`).

Each prints a markdown table and, with `--json FILE`, writes the report with its rows there (with the software
versions that made it). docs/DIAGNOSE.md says what each reads and how to read its table.
"""

import json
import sys

from rvt2cli.cli.args import COUNT, NON_NEGATIVE, POSITIVE, SEED, integer, names, task_expert


def _checkpoint_and_demos(p) -> None:
    p.add_argument("demos", nargs="+", metavar="DEMOS", help="annotated demo files or folders (rvt2 extract-keyframes)")
    p.add_argument("--checkpoint", required=True, help="run folder or checkpoint written by `rvt2 train`")
    p.add_argument("--device", default="cpu", help="policy device: cpu (default), cuda, cuda:N")
    p.add_argument("--batch-size", type=COUNT, default=8, help="observations per forward pass (default 8)")


def _target_choice(p):
    p.add_argument("journals", nargs="+", metavar="JOURNAL", help="evaluation journals (episodes.jsonl, .gz or .xz)")
    p.add_argument("--source", choices=("policy", "oracle"), default="policy", help="whose episodes (default policy)")
    p.add_argument("--via", action="store_true",
                   help="the policy learnt from experts that stop above the named target first: report its stops too")

    def build(args):
        from rvt2cli.diagnose import target_choice

        return target_choice, target_choice.report(args.journals, args.source, args.via)
    return build


def _oracle_gap(p):
    p.add_argument("journals", nargs="+", metavar="JOURNAL", help="the policy's evaluation journals (episodes.jsonl, .gz or .xz)")
    p.add_argument("--oracle", action="append", required=True, metavar="ORACLE_JOURNAL",
                   help="a journal of `rvt2 eval --oracle` on the same tasks and seeds (repeat for several)")
    p.add_argument("--tasks", type=names, help="comma-separated: only these tasks (default every task in both)")
    p.add_argument("--near-mm", type=POSITIVE, default=20.0,
                   help="count the failures whose nearest keyframe came within this many mm (default 20)")

    def build(args):
        from rvt2cli.diagnose import oracle_gap

        return oracle_gap, oracle_gap.report(args.journals, args.oracle, args.tasks, args.near_mm)
    return build


def _instruction_swap(p):
    _checkpoint_and_demos(p)
    p.add_argument("--decides-mm", type=POSITIVE, default=20.0,
                   help="an observation's words decide where it goes when its predictions spread over this (default 20)")

    def build(args):
        from rvt2cli.diagnose import instruction_swap

        return instruction_swap, instruction_swap.swap_report(args.checkpoint, args.demos, args.device, args.batch_size,
                                                              args.decides_mm)
    return build


def _phrasings(p):
    _checkpoint_and_demos(p)

    def build(args):
        from rvt2cli.diagnose import phrasings

        return phrasings, phrasings.phrasing_report(args.checkpoint, args.demos, args.device, args.batch_size)
    return build


def _paraphrase_neighbours(p):
    p.add_argument("--tasks", type=names, help="comma-separated tasks (default: every task of --task-set)")
    p.add_argument("--task-set", default="rlbench18", help="the tasks of this named set (default rlbench18)")

    def build(args):
        from rvt2cli.diagnose import paraphrase_neighbours
        from rvt2cli.tasks import tasks_of_set

        return paraphrase_neighbours, paraphrase_neighbours.report(args.tasks or tasks_of_set(args.task_set))
    return build


def _stage2_blind(p):
    _checkpoint_and_demos(p)
    p.add_argument("--min-points", type=NON_NEGATIVE, default=200,
                   help="keep stage 1's point where stage 2's box holds fewer cloud points (default 200)")

    def build(args):
        from rvt2cli.diagnose import stage2_blind

        return stage2_blind, stage2_blind.report(args.checkpoint, args.demos, args.min_points, args.device, args.batch_size)
    return build


def _stage2_view(p):
    p.add_argument("demos", nargs="+", metavar="DEMOS", help="annotated demo files or folders of insert_peg or plug_charger")
    p.add_argument("--config", default="rvt2", help="the model config whose zoom sets stage 2's box (default rvt2)")
    p.add_argument("--zoom", type=POSITIVE, help="stage 2 covers 1/ZOOM of the workspace (default: the config's)")
    p.add_argument("--aim-held", action="store_true",
                   help="centre the box where `rvt2 train --aim-held` does: the task's aim offset once the gripper holds")

    def build(args):
        from rvt2cli.diagnose import stage2_view

        return stage2_view, stage2_view.report(args.demos, args.config, args.zoom, args.aim_held)
    return build


def _insertion_stops(p):
    p.add_argument("journal", metavar="JOURNAL", help="a policy's evaluation journal (episodes.jsonl, .gz or .xz)")
    p.add_argument("--task", choices=("insert_peg", "plug_charger"), default="insert_peg", help="default insert_peg")
    p.add_argument("--searched", metavar="EVAL_DIR",
                   help="an `rvt2 eval --out` folder of the same episodes with the search (a --replay of the journal)")
    p.add_argument("--workers", type=integer(1, 256), default=2, help="parallel simulator processes (default 2)")

    def build(args):
        from rvt2cli.diagnose import insertion_stops

        return insertion_stops, insertion_stops.report(args.journal, args.task, args.searched, args.workers)
    return build


def _precision_budget(p):
    p.add_argument("--tasks", type=names, default=("insert_peg", "plug_charger"),
                   help="comma-separated (default insert_peg,plug_charger)")
    p.add_argument("--variants", type=names, default=("exact", "rot72", "rot360", "pos2"),
                   help="comma-separated: exact, rotN (bins per axis), posM (mm), turnD (degrees), aheadM (a held tool's "
                        "keyframes, mm towards where it goes next), A+B (default exact,rot72,rot360,pos2)")
    p.add_argument("--seeds", type=COUNT, default=20, help="per task and variant (default 20)")
    p.add_argument("--first-seed", type=SEED, default=10_000, help="default 10000 (demos use 0 upwards)")
    p.add_argument("--workers", type=integer(1, 256), default=2, help="parallel simulator processes (default 2)")
    p.add_argument("--no-insertion-search", dest="search", action="store_false",
                   help="push insertions straight, without the executor's search for the hole")
    p.add_argument("--search-pitch", type=POSITIVE, metavar="MM", help="the insertion search's grid pitch (default: tasks/*.toml's)")
    p.add_argument("--search-retract", type=POSITIVE, metavar="MM", help="how far each probe backs off the face (default: tasks/*.toml's)")
    p.add_argument("--expert", action="append", default=[], type=task_expert, metavar="TASK=MODULE:FUNCTION",
                   help="degrade another scripted expert's keyframes than TASK's own (repeatable), as `rvt2 record --expert`")

    def build(args):
        from rvt2cli.diagnose import precision_budget

        grid = {k: v for k, v in (("search_pitch_mm", args.search_pitch), ("search_retract_mm", args.search_retract))
                if v is not None}
        return precision_budget, precision_budget.budget(args.tasks, args.variants, args.seeds, args.first_seed,
                                                         args.workers, args.search, grid, dict(args.expert))
    return build


# name -> (its arguments, a line for `rvt2 diagnose --help`, the question it answers and what it reads); in the
# order a failing policy is looked into: the task's demands, the policy's sight, then its reading of the words
DIAGNOSTICS = {
    "precision-budget": (_precision_budget, "how precise must a policy be on a task? (the oracle, degraded)",
                         "How precise must a policy be on a task? The oracle's keyframes degraded as a policy's are (rotation "
                         "bins, millimetres, degrees) on the same seeds.", "the tasks' experts and the executor, no checkpoint"),
    "stage2-blind": (_stage2_blind, "where stage 2's zoomed box sees nothing (checkpoint + demos)",
                     "Where does stage 2's zoomed box hold nothing to place the keyframe by, and what would keeping "
                     "stage 1's point there give?", "a checkpoint and annotated demos"),
    "stage2-view": (_stage2_view, "what stage 2's box sees of the goal at each keyframe (insertion demos)",
                    "How much of the goal object does stage 2's box see at each keyframe of insert_peg or plug_charger "
                    "demos, centred on the TCP or, with --aim-held, on the held object's aim?", "annotated demos"),
    "insertion-stops": (_insertion_stops, "where a policy's first insertion stops, pushed straight (journal)",
                        "Where does a policy's first insertion leave the held object when it is pushed straight, and "
                        "which of those does the executor's insertion search bring in?", "an evaluation journal"),
    "oracle-gap": (_oracle_gap, "which of the expert's keyframes a failing policy misses (journals)",
                   "Which of the expert's keyframes does a failing policy never reach? Each keyframe of the oracle's "
                   "episode against the policy's nearest on the same task and seed, successes and failures apart.",
                   "the policy's and the oracle's evaluation journals"),
    "instruction-swap": (_instruction_swap, "does the instruction decide where the policy goes? (checkpoint + demos)",
                         "Does the instruction decide where the policy goes? Each observation predicted under its own "
                         "instruction and under every other variation's.", "a checkpoint and annotated demos"),
    "phrasings": (_phrasings, "which phrasings the policy misreads, and where (checkpoint + demos)",
                  "Where does a phrasing the policy misreads move its keyframes? Each keyframe start predicted under "
                  "every phrasing of its variation, trained and held out.", "a checkpoint and annotated demos"),
    "paraphrase-neighbours": (_paraphrase_neighbours, "does the encoder place each paraphrase nearest its own variation? (tasks)",
                              "Does the instruction encoder itself place each held-out paraphrase nearest a trained "
                              "phrasing of its own variation? Before any training: the words as the policy reads them.",
                              "the tasks' phrasings, no checkpoint"),
    "target-choice": (_target_choice, "which target each push went for: the named colour or another (journals)",
                      "Which target did each push of reach_and_drag and slide_block_to_color_target go for, the named "
                      "colour or another?", "evaluation journals"),
}


def register(subparsers) -> None:
    p = subparsers.add_parser("diagnose", help="why a policy fails: analyses of your journals, checkpoints and demos",
                              description="Why a policy fails, one question per NAME; each prints a table (see "
                                          "docs/DIAGNOSE.md) and writes it with its rows to --json FILE.")
    sub = p.add_subparsers(dest="diagnostic", metavar="NAME")
    for name, (arguments, line, question, reads) in DIAGNOSTICS.items():
        q = sub.add_parser(name, help=line, description=f"{question} Reads {reads}; docs/DIAGNOSE.md explains the table.")
        build = arguments(q)
        q.add_argument("--json", metavar="FILE", help="write the report, with its rows, here too")
        q.set_defaults(build=build)
    p.set_defaults(run=run, diagnose_parser=p)


def run(args) -> int:
    if args.diagnostic is None:
        args.diagnose_parser.print_help(sys.stderr)
        return 2
    from pathlib import Path

    from rvt2cli.atomic import atomic_open, check_folder_can_be_made, ensure_folder
    from rvt2cli.data.provenance import software_versions

    if args.json:   # a bad --json is one line before the analysis runs
        check_folder_can_be_made(Path(args.json).parent, "folder of --json")
    module, report = args.build(args)
    print(module.markdown(report), end="")
    if args.json:
        ensure_folder(Path(args.json).parent, "folder of --json")
        with atomic_open(args.json, "w") as f:
            json.dump({"diagnostic": args.diagnostic, "software": software_versions("torch", "mani-skill", "sapien"),
                       **report}, f, indent=1)
    return 0
