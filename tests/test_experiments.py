"""experiments/*.toml through benchmarks/experiment.py: every command an experiment file turns into is
one the real `rvt2` parsers accept, so a renamed or removed option fails here, not on a GPU machine."""

import json
import lzma
import sys
from pathlib import Path

import pytest

from benchmarks import experiment as runner
from rvt2cli.cli import build_parser
from rvt2cli.cli.train import options_from
from rvt2cli.errors import UserError
from rvt2cli.runtime import usable_cores
from rvt2cli.train.run_folder import model_config

EXPERIMENT_FILES = sorted(runner.EXPERIMENTS.glob("*.toml"))
KIT_REHEARSAL = runner.EXPERIMENTS.parent / "scripts" / "offline-gpu-host" / "rehearse_via.toml"   # not a result


def rvt2_arguments(argv: list[str]) -> list[str]:
    """The arguments after the launcher: `rvt2 ...` or `torchrun ... -m rvt2cli ...`."""
    return argv[1:] if argv[0] == "rvt2" else argv[argv.index("rvt2cli") + 1:]


def test_there_are_experiments():
    assert {p.stem for p in EXPERIMENT_FILES} >= {"rvt2_25demos", "rvt2_10demos"}


@pytest.mark.parametrize("path", [*EXPERIMENT_FILES, KIT_REHEARSAL], ids=lambda p: p.stem)
@pytest.mark.parametrize("gpus", [1, 2])
def test_every_command_parses_with_the_cli(path, gpus, tmp_path):
    experiment = runner.load(path)
    settings = runner.Settings(out=tmp_path, workers=3, gpus=gpus)
    run = runner.commands(experiment, settings)
    declared = {"record", "train", "eval"} | ({"heldout", "offline"} if "heldout" in experiment else set()) \
        | ({"oracle"} if "oracle" in experiment else set())
    assert [phase for phase in runner.PHASES if any(p == phase for p, _ in run)] == \
        [phase for phase in runner.PHASES if phase in declared]
    parser = build_parser()
    for phase, argv in run:
        arguments = rvt2_arguments(argv)
        args = parser.parse_args(arguments)  # an unknown option or a bad value exits here
        assert args.command == arguments[0]
        if phase == "train":
            assert args.batch_size * gpus == experiment["train"]["batch_size"]
            assert args.steps == experiment["train"]["steps"]
            assert (argv[0] == "torchrun") == (gpus > 1)
            model_config(options_from(args))  # the options suit the model config (one stage or two)


@pytest.mark.parametrize("path", [p for p in EXPERIMENT_FILES if "published" in runner.load(p)], ids=lambda p: p.stem)
def test_published_raw_files_are_in_the_tree(path):
    published = runner.load(path)["published"]
    for raw in published["raw"]:
        assert (runner.REPOSITORY / raw).exists(), raw


def test_evaluation_ranges_and_extra_evaluations(tmp_path):
    """rvt2_18: 100 seeds as two disjoint ranges of 50, each its own report, the paraphrases on the first, and
    four tasks with stage 2's point even where its box is nearly empty (the published model's setting)."""
    run = runner.commands(runner.load(runner.resolve("rvt2_18")), runner.Settings(out=tmp_path, workers=60))
    evals = [build_parser().parse_args(rvt2_arguments(argv)) for phase, argv in run if phase == "eval"]
    assert [(a.seed, a.episodes, Path(a.out).name, a.paraphrases, a.workers) for a in evals] == [
        (10000, 50, "seed0_from10000", False, 18), (10050, 50, "seed0_from10050", False, 17),
        (10000, 50, "seed0_paraphrases", True, 17), (10000, 100, "seed0_stage2_everywhere", False, 8)]
    # run at the same time, the workers shared by episodes: 900, 900, 900 and 4 tasks x 100
    assert len(evals[-1].tasks) == 4 and "stack_blocks" in evals[-1].tasks and evals[-1].stage2_min_points == 0
    assert all(a.stage2_min_points is None for a in evals[:-1])  # the checkpoint's own


def test_chosen_evaluations_run_alone_with_every_worker(tmp_path, capsys):
    """--evaluations main: the two ranges alone, sharing all 60 workers (a machine short of time); the extra
    evaluations later by name; a name the file lacks is one line that lists the ones it has."""
    experiment = runner.load(runner.resolve("rvt2_18"))

    def evals(chosen):
        run = runner.commands(experiment, runner.Settings(out=tmp_path, workers=60, evaluations=chosen))
        return [build_parser().parse_args(rvt2_arguments(argv)) for phase, argv in run if phase == "eval"]

    assert [(Path(a.out).name, a.seed, a.episodes, a.workers) for a in evals(("main",))] == [
        ("seed0_from10000", 10000, 50, 30), ("seed0_from10050", 10050, 50, 30)]
    assert [(Path(a.out).name, a.paraphrases, a.workers) for a in evals(("paraphrases", "stage2_everywhere"))] == [
        ("seed0_paraphrases", True, 42), ("seed0_stage2_everywhere", False, 18)]
    assert runner.main(["rvt2_18", "--evaluations", "main,paraphrase"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no evaluation paraphrase; this experiment has main, paraphrases, stage2_everywhere" in err
    assert len(err.splitlines()) == 1


def test_an_interrupted_evaluation_resumes_with_workers_for_the_episodes_it_has_left(tmp_path):
    """rvt2_18's first range as the first GPU machine left it, 367 of its 900 episodes run (the first lines of
    the published journal, which resumed it): it resumes, and the four evaluations share 60 workers as
    533 : 900 : 900 : 400 episodes."""
    journal = tmp_path / "evals" / "seed0_from10000" / "episodes.jsonl"
    journal.parent.mkdir(parents=True)
    published = runner.REPOSITORY / "benchmarks/results/rvt2_18_h100x4/evals/seed0_from10000/episodes.jsonl.xz"
    journal.write_text("".join(lzma.decompress(published.read_bytes()).decode().splitlines(keepends=True)[:1 + 367]))
    run = runner.commands(runner.load(runner.resolve("rvt2_18")), runner.Settings(out=tmp_path, workers=60))
    evals = [build_parser().parse_args(rvt2_arguments(argv)) for phase, argv in run if phase == "eval"]
    assert [(Path(a.out).name, a.workers, a.resume) for a in evals] == [
        ("seed0_from10000", 11, True), ("seed0_from10050", 20, False), ("seed0_paraphrases", 20, False),
        ("seed0_stage2_everywhere", 9, False)]


def test_workers_are_shared_in_proportion_to_episodes():
    assert runner.share_workers(60, [50, 50, 50]) == [20, 20, 20]
    assert runner.share_workers(10, [100, 50, 50]) == [5, 3, 2]   # the first of equal remainders
    assert runner.share_workers(2, [25, 25, 25]) == [1, 1, 1]   # never none
    assert runner.share_workers(7, [25]) == [7]


def test_an_evaluation_phase_runs_its_commands_at_the_same_time(tmp_path, capsys):
    """Each command stays until the other has started; one that fails lets the other finish, and the phase
    fails with its exit code. The other phases run their commands in turn."""
    wait_for = ("import pathlib, sys, time; me, other, code = sys.argv[1:]; pathlib.Path(me).touch(); "
                "deadline = time.time() + 20\nwhile not pathlib.Path(other).exists() and time.time() < deadline: time.sleep(0.05)\n"
                "pathlib.Path(me + '.saw').write_text(str(pathlib.Path(other).exists())); sys.exit(int(code))")
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    run = [("eval", [sys.executable, "-c", wait_for, a, b, "0"]), ("eval", [sys.executable, "-c", wait_for, b, a, "3"]),
           ("offline", [sys.executable, "-c", "pass"])]
    assert runner.execute(run, tmp_path / "out") == 3
    assert (tmp_path / "a.saw").read_text() == "True" and (tmp_path / "b.saw").read_text() == "True"
    assert "eval failed (exit code 3)" in capsys.readouterr().err
    assert not (tmp_path / "out" / "phases.tsv").exists()    # the failed phase is not timed, the next not run
    c, d = str(tmp_path / "c"), str(tmp_path / "d")
    in_turn = [("offline", [sys.executable, "-c", wait_for.replace("20", "1"), c, d, "0"]),
               ("offline", [sys.executable, "-c", wait_for.replace("20", "1"), d, c, "0"])]
    assert runner.execute(in_turn, tmp_path / "out") == 0
    assert (tmp_path / "c.saw").read_text() == "False"   # the second had not started
    assert (tmp_path / "out" / "phases.tsv").read_text().split("\t")[0] == "offline"


def test_phases_alongside_training_run_while_it_trains_and_the_evaluation_waits_for_them(tmp_path):
    """The oracle starts with the training (which sees it start), runs on after the training has ended, and the
    evaluation starts only once it has ended; each phase is timed on its own."""
    sees = ("import pathlib, sys, time; other = pathlib.Path(sys.argv[1]); deadline = time.time() + 20\n"
            "while not other.exists() and time.time() < deadline: time.sleep(0.05)\n"
            "pathlib.Path(sys.argv[2]).write_text(str(other.exists()))")
    slow = "import pathlib, sys, time; pathlib.Path(sys.argv[1]).touch(); time.sleep(1); pathlib.Path(sys.argv[2]).touch()"
    started, ended = tmp_path / "oracle_started", tmp_path / "oracle_ended"
    run = [("record", [sys.executable, "-c", "pass"]),
           ("train", [sys.executable, "-c", sees, str(started), str(tmp_path / "train_saw")]),
           ("eval", [sys.executable, "-c", sees, str(ended), str(tmp_path / "eval_saw")]),
           ("oracle", [sys.executable, "-c", slow, str(started), str(ended)])]
    assert runner.execute(run, tmp_path / "out", alongside=("oracle",)) == 0
    assert (tmp_path / "train_saw").read_text() == "True" and (tmp_path / "eval_saw").read_text() == "True"
    assert sorted(line.split("\t")[0] for line in (tmp_path / "out" / "phases.tsv").read_text().splitlines()) == [
        "eval", "oracle", "record", "train"]
    failing = [("train", [sys.executable, "-c", "pass"]), ("eval", [sys.executable, "-c", "pass"]),
               ("oracle", [sys.executable, "-c", "raise SystemExit(5)"])]
    assert runner.execute(failing, tmp_path / "failing", alongside=("oracle",)) == 5   # and no evaluation ran
    assert [line.split("\t")[0] for line in (tmp_path / "failing" / "phases.tsv").read_text().splitlines()] == ["train"]


def test_an_evaluation_of_the_held_out_variations_gets_workers_for_the_tasks_that_have_them(tmp_path):
    """rvt2_18_onegpu_unseen: the seen variations of 18 tasks x 50 seeds beside the held-out ones, which only four
    tasks have (`rvt2 eval --variations held-out` leaves the others out): 900 episodes against 400, so 10 and 5 of
    15 workers, not the 18 x 100 episodes the seeds alone would say; both replay each worker's step as a CUDA graph."""
    run = runner.commands(runner.load(runner.resolve("rvt2_18_onegpu_unseen")), runner.Settings(out=tmp_path, workers=15),
                          ("eval",))
    evals = [build_parser().parse_args(rvt2_arguments(argv)) for phase, argv in run if phase == "eval"]
    assert [(Path(a.out).name, a.episodes, a.variations, a.workers, a.cuda_graph) for a in evals] == [
        ("seed0", 50, "seen", 10, True), ("seed0_unseen", 100, "held-out", 5, True)]
    assert runner.tasks_evaluated(["close_jar", "open_drawer", "stack_blocks"], {"variations": "held-out"}) == 2
    assert runner.tasks_evaluated(["close_jar", "open_drawer"], {"tasks": "open_drawer"}) == 1


def test_the_one_gpu_run_leaves_two_workers_to_the_training(tmp_path):
    experiment = runner.load(runner.resolve("rvt2_18_onegpu"))
    run = runner.commands(experiment, runner.Settings(out=tmp_path, workers=15))
    workers = {argv[argv.index("--out") + 1].split("/")[-1]: int(argv[argv.index("--workers") + 1])
               for _, argv in run if "--workers" in argv}
    assert workers == {"demos": 15, "heldout": 13, "oracle": 13, "seed0_from10000": 8, "seed0_from10050": 7}
    alone = runner.commands(experiment, runner.Settings(out=tmp_path, workers=15), ("oracle",))
    assert alone[0][1][alone[0][1].index("--workers") + 1] == "15"   # no training beside it: every worker


def test_another_schedule_on_validation_seeds(tmp_path, capsys):
    """--steps trains another schedule into its own folder; --eval-seeds evaluates it on those seeds alone."""
    settings = runner.Settings(out=tmp_path, workers=4, steps=3000, eval_seeds=(20000, 20049))
    run = runner.commands(runner.load(runner.resolve("rvt2_18_onegpu")), settings, ("train", "eval"))
    train = build_parser().parse_args(rvt2_arguments(next(argv for phase, argv in run if phase == "train")))
    assert train.steps == 3000 and train.warmup == 200
    evals = [build_parser().parse_args(rvt2_arguments(argv)) for phase, argv in run if phase == "eval"]
    assert [(Path(a.out).name, a.episodes, a.seed, a.workers) for a in evals] == [("seed0_from20000", 50, 20000, 4)]
    assert runner.main(["rvt2_18_onegpu", "--steps", "3000", "--phase", "train"]) == 0
    assert "data/experiments/rvt2_18_onegpu_3000steps/runs/seed0" in capsys.readouterr().out
    assert runner.main(["rvt2_18_onegpu", "--eval-seeds", "20049-20000"]) == 2
    assert "--eval-seeds 20049-20000: give FIRST-LAST" in capsys.readouterr().err


def test_a_curve_evaluates_earlier_checkpoints_beside_the_last(tmp_path, capsys):
    """--eval-steps evaluates the checkpoints `rvt2 train` keeps on the way (save-every), each into its own folder, on
    the same seeds as the last, all at once with the workers shared; a step the training keeps no checkpoint of is refused."""
    settings = runner.Settings(out=tmp_path, workers=9, steps=6000, eval_seeds=(20000, 20049), eval_steps=(2000, 4000))
    run = runner.commands(runner.load(runner.resolve("rvt2_18_onegpu")), settings, ("train", "eval"))
    train = build_parser().parse_args(rvt2_arguments(next(argv for phase, argv in run if phase == "train")))
    evals = [build_parser().parse_args(rvt2_arguments(argv)) for phase, argv in run if phase == "eval"]
    assert [(Path(a.out).name, a.checkpoint.removeprefix(str(tmp_path)), a.seed, a.episodes, a.workers) for a in evals] == [
        ("seed0_from20000", "/runs/seed0", 20000, 50, 3),
        ("seed0_from20000_step2000", "/runs/seed0/checkpoints/step_0002000", 20000, 50, 3),
        ("seed0_from20000_step4000", "/runs/seed0/checkpoints/step_0004000", 20000, 50, 3)]
    assert train.save_every == 1000 and train.steps == 6000
    assert runner.runs_together("eval", [argv for phase, argv in run if phase == "eval"])
    assert runner.main(["rvt2_18_onegpu", "--steps", "6000", "--eval-steps", "2500,6000"]) == 2
    assert "--eval-steps 2500,6000: the training keeps a checkpoint every 1000 steps before its last (6000)" in capsys.readouterr().err
    assert runner.main(["rvt2_18_onegpu", "--eval-steps", "two"]) == 2
    assert "--eval-steps two: give whole numbers" in capsys.readouterr().err


def test_a_curve_may_take_fewer_seeds_at_the_earlier_checkpoints(tmp_path, capsys):
    """--curve-episodes 25: the earlier checkpoints on the first 25 seeds of each task, the last on all 50; the workers
    follow the episodes; without --eval-steps it is refused."""
    settings = runner.Settings(out=tmp_path, workers=30, eval_seeds=(20000, 20049), eval_steps=(1500, 3000, 4500),
                               curve_episodes=25)
    run = runner.commands(runner.load(runner.resolve("rvt2_18")), settings, ("eval",))
    evals = [build_parser().parse_args(rvt2_arguments(argv)) for _, argv in run]
    assert [(Path(a.out).name, a.seed, a.episodes, a.workers) for a in evals] == [
        ("seed0_from20000", 20000, 50, 12), ("seed0_from20000_step1500", 20000, 25, 6),
        ("seed0_from20000_step3000", 20000, 25, 6), ("seed0_from20000_step4500", 20000, 25, 6)]
    assert runner.main(["rvt2_18", "--curve-episodes", "25"]) == 2
    assert "--curve-episodes 25: give a whole number of at least 1, with --eval-steps" in capsys.readouterr().err


def test_an_experiment_extends_another_with_only_what_it_changes(tmp_path):
    """rvt2_18_onegpu_via is rvt2_18_onegpu with two tasks' experts and 3,000 steps: every other command is the same."""
    base, via = (runner.load(runner.resolve(n)) for n in ("rvt2_18_onegpu", "rvt2_18_onegpu_via"))
    assert via["train"]["options"] == base["train"]["options"] and via["published"]["raw"] != base["published"]["raw"]
    settings = runner.Settings(out=tmp_path, workers=15)
    base_run = runner.commands(base, runner.Settings(out=tmp_path, workers=15, steps=3000))
    via_run = runner.commands(via, settings)
    differing = [(a, b) for (_, a), (_, b) in zip(base_run, via_run) if a != b]
    assert len(base_run) == len(via_run) and len(differing) == 1   # the training demos: the held-out tasks keep their experts
    record = build_parser().parse_args(rvt2_arguments(differing[0][1]))
    assert dict(record.expert) == {task: f"rvt2cli.record.rlbench18.{task}:expert_via_target"
                                   for task in ("reach_and_drag", "slide_block_to_color_target")}
    circle = tmp_path / "a.toml"
    circle.write_text(f'extends = "{circle}"\nname = "a"\n')
    with pytest.raises(UserError, match="extends .* which extends it again"):
        runner.load(circle)
    orphan = tmp_path / "b.toml"
    orphan.write_text('extends = "rvt2_18_onegpu"\n')
    with pytest.raises(UserError, match="gives no 'name' of its own"):
        runner.load(orphan)
    orphan.write_text('extends = "rvt2_18_onegpu"\nname = "b"\n')
    assert "published" not in runner.load(orphan)   # another file's results are not this one's


def test_another_renderer_for_every_phase_and_its_own_folder(capsys):
    """--renderer replaces the file's Vulkan driver in every command's environment, and the default folder says so."""
    assert runner.main(["rvt2_18", "--renderer", "nvidia", "--eval-seeds", "20000-20049", "--eval-steps", "1500,3000,4500"]) == 0
    printed = capsys.readouterr().out
    assert "export RVT2_VULKAN=nvidia" in printed and "lavapipe" not in printed
    assert "data/experiments/rvt2_18_nvidia/evals/seed0_from20000_step4500" in printed
    assert "runs/seed0/checkpoints/step_0001500 " in printed
    assert runner.environment(runner.load(runner.resolve("rvt2_18")), 4)["RVT2_VULKAN"] == "lavapipe"


def test_evaluations_side_by_side_share_the_cores_as_they_share_the_workers(tmp_path, monkeypatch):
    """Each of rvt2-18's three evaluations gets a third of the workers; lavapipe's threads per worker are
    counted over all of them, in every command's environment, not over each command's own third."""
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    experiment = runner.load(runner.resolve("rvt2_18"))
    workers = 3 * max(1, usable_cores() // 2)
    gained = runner.environment(experiment, workers)
    assert gained == {"RVT2_VULKAN": "lavapipe", "LP_NUM_THREADS": str(max(1, usable_cores() // workers))}
    shown = "import os, sys; open(sys.argv[1], 'w').write(os.environ['LP_NUM_THREADS'])"
    run = [("eval", [sys.executable, "-c", shown, str(tmp_path / name)]) for name in "abc"]
    assert runner.execute(run, tmp_path / "out", gained) == 0
    assert {(tmp_path / name).read_text() for name in "abc"} == {gained["LP_NUM_THREADS"]}
    monkeypatch.setenv("LP_NUM_THREADS", "5")
    assert "LP_NUM_THREADS" not in runner.environment(experiment, workers)   # the caller's own is kept


def test_the_unseen_split_leaves_held_out_variations_out_of_the_training_demos(tmp_path):
    run = runner.commands(runner.load(runner.resolve("rvt2_18_unseen")), runner.Settings(out=tmp_path, workers=2))
    record = [argv for phase, argv in run if phase == "record" and argv[1] == "record"]
    assert len(record) == 1 and record[0][-1] == "--hold-out-variations"
    evals = [argv for phase, argv in run if phase == "eval"]
    assert [argv[argv.index("--variations") + 1] for argv in evals] == ["seen", "held-out"]
    assert not any("--hold-out-variations" in argv for argv in runner.commands(
        runner.load(runner.resolve("rvt2_18")), runner.Settings(out=tmp_path, workers=2)))


def test_experts_named_in_the_file_record_the_training_and_the_held_out_demos(tmp_path):
    run = runner.commands(runner.load(runner.resolve("rvt2_18_colour_via")), runner.Settings(out=tmp_path, workers=2))
    records = [argv for phase, argv in run if argv[1] == "record"]
    assert [phase for phase, argv in run if argv[1] == "record"] == ["record", "heldout"]
    for argv in records:
        experts = [argv[i + 1] for i, a in enumerate(argv) if a == "--expert"]
        assert experts == [f"{task}=rvt2cli.record.rlbench18.{task}:expert_via_target"
                           for task in ("reach_and_drag", "slide_block_to_color_target")]


def test_print_is_the_default_and_names_each_phase(capsys, monkeypatch):
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    assert runner.main(["rvt2_25demos", "--phase", "train,eval", "--workers", "4"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[:3] == ["export RVT2_VULKAN=nvidia", f"export LP_NUM_THREADS={max(1, usable_cores() // 4)}",
                         "# train"] and "# eval" in lines   # the published renderer, lavapipe's threads
    train = lines[3]
    assert train.startswith("rvt2 train ") and "--task-weights insert_peg=3,plug_charger=3" in train
    assert not Path("data/experiments/rvt2_25demos").exists()  # printing creates nothing


@pytest.mark.parametrize("text, message", [
    ("name = 'x'\ntasks = ['push_cube']\n[record]\ndemos_per_task = 1\n[train]\nsteps = 1\nbatch = 4\n[eval]\nepisodes_per_task = 1\n",
     "unknown key 'batch' in [train]"),
    ("name = 'x'\ntasks = ['push_cubes']\n[record]\ndemos_per_task = 1\n[train]\nsteps = 1\n[eval]\nepisodes_per_task = 1\n",
     "unknown task 'push_cubes'"),
    ("name = 'x'\ntasks = ['push_cube']\n[record]\ndemos_per_task = 1\n[train]\nseeds = [0]\n[eval]\nepisodes_per_task = 1\n",
     "[train] has no 'steps'"),
    ("name = 'x'\ntasks = [\n", "not valid TOML"),
    ("name = 'x'\ntasks = ['push_cube']\n[record]\ndemos_per_task = 1\nhold_out_variations = 'yes'\n[train]\nsteps = 1\n"
     "[eval]\nepisodes_per_task = 1\n", "[record] hold_out_variations takes true or false"),
    ("name = 'x'\ntasks = ['push_cube']\n[record]\ndemos_per_task = 1\nexperts = { pull_cube = 'm:f' }\n[train]\nsteps = 1\n"
     "[eval]\nepisodes_per_task = 1\n", "[record] experts names 'pull_cube', which is not among the file's tasks"),
    ("name = 'x'\ntasks = ['push_cube']\n[record]\ndemos_per_task = 1\nexperts = { push_cube = 'nocolon' }\n[train]\n"
     "steps = 1\n[eval]\nepisodes_per_task = 1\n", "[record] experts takes task = \"module:function\" pairs"),
    ("name = 'x'\nalongside_training = ['eval']\ntasks = ['push_cube']\n[record]\ndemos_per_task = 1\n[train]\nsteps = 1\n"
     "[eval]\nepisodes_per_task = 1\n", "alongside_training = ['eval']; give a list of some of heldout, oracle"),
    ("name = 'x'\nrenderer = 'mesa'\ntasks = ['push_cube']\n[record]\ndemos_per_task = 1\n[train]\nsteps = 1\n[eval]\n"
     "episodes_per_task = 1\n", "renderer = 'mesa'; choose one of auto, nvidia, lavapipe"),
    ("name = 'x'\ntasks = ['push_cube']\n[record]\ndemos_per_task = 1\n[train]\nsteps = 1\n[eval]\nepisodes_per_task = 100\n"
     "ranges = 3\n", "[eval] ranges = 3 does not divide episodes_per_task = 100"),
    ("name = 'x'\ntasks = ['push_cube']\n[record]\ndemos_per_task = 1\n[train]\nsteps = 1\n[eval]\nepisodes_per_task = 2\n"
     "[eval.extra.p]\nseeds = 3\n", "unknown key 'seeds' in [eval.extra.p]"),
])
def test_a_bad_file_is_one_line_and_exit_code_2(tmp_path, capsys, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert runner.main([str(path)]) == 2
    err = capsys.readouterr().err
    assert message in err and str(path) in err and len(err.strip().splitlines()) == 1


def test_gpus_must_divide_the_batch(capsys):
    assert runner.main(["rvt2_25demos", "--gpus", "5"]) == 2
    assert "does not divide the global batch 192" in capsys.readouterr().err


@pytest.mark.sim
def test_run_executes_a_phase_and_times_it(tmp_path, capsys, monkeypatch):
    """--run on the real simulator: the oracle of one push_cube episode."""
    path = tmp_path / "tiny.toml"
    path.write_text("name = 'tiny'\nrenderer = 'lavapipe'\ntasks = ['push_cube']\n[record]\ndemos_per_task = 1\n"
                    "[train]\nsteps = 1\n[eval]\nepisodes_per_task = 1\n[oracle]\nepisodes_per_task = 1\nfirst_seed = 10000\n")
    out = tmp_path / "out"
    code = runner.main([str(path), "--run", "--phase", "oracle", "--workers", "1", "--out", str(out),
                        "--rvt2", f"{sys.executable} -m rvt2cli"])
    assert code == 0
    report = json.loads((out / "oracle" / "eval.json").read_text())
    assert report["episodes_per_task"] == 1 and report["seed"] == 10000
    assert [line.split("\t")[0] for line in (out / "phases.tsv").read_text().splitlines()] == ["oracle"]
    capsys.readouterr()
    monkeypatch.setenv("LP_NUM_THREADS", "3")   # the caller's own limit is kept, and not printed
    assert runner.main([str(path), "--phase", "oracle"]) == 0   # printed: the renderer first
    assert capsys.readouterr().out.startswith("export RVT2_VULKAN=lavapipe\n# oracle\n")


def test_a_training_stopped_at_its_time_limit_resumes_when_the_phase_runs_again(tiny_dataset, tmp_path, capsys):
    """--time-limit on the real `rvt2 train`: the phase stops with exit code 75 and one line saying how to go on,
    is timed as train_stopped, and no later phase runs; run again without the limit, the same command gains
    --resume and the run ends at its last step."""
    import shutil

    path = tmp_path / "tiny.toml"
    path.write_text("name = 'tiny'\ntasks = ['stack_cube']\n[record]\ndemos_per_task = 2\n"
                    "[train]\nconfig = 'small'\nsteps = 4\nbatch_size = 8\n"
                    "options = { log-every = 2, val-episodes = 0, max-points = 20000, no-augment = true }\n"
                    "[eval]\nepisodes_per_task = 1\n")
    out = tmp_path / "out"
    shutil.copytree(tiny_dataset, out / "demos")
    given = [str(path), "--out", str(out), "--rvt2", f"{sys.executable} -m rvt2cli"]
    assert runner.main([*given, "--run", "--phase", "train,eval", "--time-limit", "1e-9"]) == 75
    err = capsys.readouterr().err
    assert "stopped at its --time-limit" in err and "run the train phase again" in err and "Traceback" not in err
    assert [line.split("\t")[0] for line in (out / "phases.tsv").read_text().splitlines()] == ["train_stopped"]
    assert not (out / "evals").exists()
    run = json.loads((out / "runs" / "seed0" / "run.json").read_text())
    assert run["out_of_time"] is True and run["steps"] == 2
    assert runner.main([*given, "--phase", "train"]) == 0   # printed
    assert "--resume --no-progress" in capsys.readouterr().out
    assert runner.main([*given, "--run", "--phase", "train"]) == 0
    run = json.loads((out / "runs" / "seed0" / "run.json").read_text())
    assert run["out_of_time"] is False and run["steps"] == 4
    assert [line.split("\t")[0] for line in (out / "phases.tsv").read_text().splitlines()] == ["train_stopped", "train"]
    assert runner.main([*given, "--run", "--time-limit", "0"]) == 2
    assert capsys.readouterr().err.strip().endswith("--time-limit 0: give the minutes a training may take, more than 0")


def test_success_against_training_time_from_published_runs(tmp_path):
    """benchmarks.success_curve reads experiment folders as published (xz journals, train/): one point per
    evaluated checkpoint, the training's minutes to it from run.json and train.csv, a chart and the points."""
    from benchmarks import success_curve

    results = runner.REPOSITORY / "benchmarks/results"
    two, three = (results / f"rvt2_18_onegpu_via_{name}" for name in ("2000steps_h200x2", "3000steps"))
    chart, points = tmp_path / "curve.png", tmp_path / "curve.json"
    assert success_curve.main(["--model", f"via={two}+{three}", "--seeds", "20000", "--chart", str(chart),
                               "--json", str(points), "--x", "steps"]) == 0
    via = json.loads(points.read_text())["via"]
    assert [(p["step"], p["successes"], p["episodes"]) for p in via] == [(2000, 626, 900), (3000, 701, 900)]
    for p, folder in zip(via, (two, three)):
        run = json.loads(lzma.decompress((folder / "train/run.json.xz").read_bytes()))
        assert abs(p["train_minutes"] - run["seconds"] / 60) < 1e-9   # the last checkpoint: the whole training
    assert via[0]["ci95"][0] < via[0]["rate"] < via[0]["ci95"][1] and chart.read_bytes()[:4] == b"\x89PNG"
    # a curve of one training, its journals kept as xz: the earlier checkpoints on fewer seeds, each one's minutes
    # up to it, in order
    curve = results / "rvt2_18_via_h200x4"
    assert success_curve.main(["--model", f"curve={curve}", "--seeds", "20000", "--json", str(points)]) == 0
    points_of_curve = json.loads(points.read_text())["curve"]
    assert [(p["step"], p["episodes"]) for p in points_of_curve] == [(1500, 450), (3000, 450), (4500, 450), (6000, 900)]
    minutes = [p["train_minutes"] for p in points_of_curve]
    assert minutes == sorted(minutes) and abs(minutes[-1] - json.loads(lzma.decompress((curve / "train/run.json.xz").read_bytes()))["seconds"] / 60) < 1e-9
    with pytest.raises(SystemExit, match="LABEL=DIR"):
        success_curve.main(["--model", str(two)])
    # the reported seeds' two ranges pooled into one point per checkpoint, or one range alone
    rvt = results / "rvt_18_onegpu_h200x2"
    for seeds, expected in (("10000,10050", [(850, 214, 1800, [10000, 10050])]), ("10000", [(850, 104, 900, [10000])])):
        assert success_curve.main(["--model", f"rvt={rvt}", "--seeds", seeds, "--json", str(points)]) == 0
        assert [(p["step"], p["successes"], p["episodes"], p["first_seeds"])
                for p in json.loads(points.read_text())["rvt"]] == expected
    with pytest.raises(SystemExit, match="--seeds FIRST"):
        success_curve.main(["--model", f"rvt={rvt}"])


SCHEDULES = runner.EXPERIMENTS.parent / "scripts" / "schedules_side_by_side.sh"
TINY_EXPERIMENT = """name = "tiny_schedules"
summary = "two schedules of a tiny policy on one recording"
tasks = ["push_cube"]
[record]
demos_per_task = 1
[train]
config = "small"
steps = 2
batch_size = 4
[train.options]
warmup = 1
val-episodes = 0
[eval]
episodes_per_task = 1
"""


@pytest.mark.sim
def test_schedules_side_by_side_record_once_and_train_and_evaluate_each_schedule(tmp_path):
    """scripts/schedules_side_by_side.sh on a machine without a GPU: one recording, the schedules one after
    another in folders of their own (their demos a link to it), each evaluated on the validation seeds."""
    import subprocess

    file = tmp_path / "tiny_schedules.toml"
    file.write_text(TINY_EXPERIMENT)
    env = {**__import__("os").environ, "ROOT": str(tmp_path / "x"), "WORKERS": "1", "VALIDATION": "20000-20000",
           "CUDA_VISIBLE_DEVICES": "", "PYTHON": sys.executable}
    r = subprocess.run(["bash", str(SCHEDULES), str(file), "1,2", "--device", "cpu", "--rvt2", f"{sys.executable} -m rvt2cli"],
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    recording = tmp_path / "x" / "tiny_schedules"
    assert len(list((recording / "demos").glob("*.mcap"))) == 1
    for steps in (1, 2):
        folder = tmp_path / "x" / f"tiny_schedules_{steps}steps"
        assert (folder / "demos").resolve() == (recording / "demos").resolve()
        assert json.loads((folder / "runs" / "seed0" / "run.json").read_text())["steps"] == steps
        report = json.loads((folder / "evals" / "seed0_from20000" / "eval.json").read_text())
        assert [(e["task"], e["seed"]) for e in report["episodes"]] == [("push_cube", 20000)]


@pytest.mark.parametrize("args, message", [(["nope.toml", "1,2"], "no such experiment file"),
                                           (["experiments/rvt2_18_onegpu_via.toml", "3500,x"], "give numbers of steps")])
def test_schedules_side_by_side_refuses_bad_input_in_one_line(args, message):
    import subprocess

    r = subprocess.run(["bash", str(SCHEDULES), *args], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
