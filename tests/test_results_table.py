"""benchmarks/results_table.py beside the paper: the RVT-2 paper's RLBench-18 column
(benchmarks/paper_rlbench18.toml) against rvt2-18's task set, and a table with it built from a real
evaluation journal (the rvt2-18 oracle's 900 episodes, published in benchmarks/results/)."""

import json
import lzma
import tomllib

import pytest

from benchmarks import results_table
from benchmarks.experiment import REPOSITORY
from rvt2cli.eval.report import build_report
from rvt2cli.tasks import get_task, tasks_of_set

PAPER = REPOSITORY / "benchmarks" / "paper_rlbench18.toml"
ORACLE = REPOSITORY / "benchmarks" / "results" / "rlbench18_oracle_50"


@pytest.mark.parametrize("model", ["rvt2", "rvt", "peract"])
def test_the_paper_column_names_every_rvt2_18_task_and_keeps_its_average(model):
    figures = tomllib.loads(PAPER.read_text())[model]
    tasks = {k: v for k, v in figures.items() if k != "average"}
    assert set(tasks) == set(tasks_of_set("rlbench18"))
    means = [mean for mean, _std in tasks.values()]
    assert sum(means) / len(means) == pytest.approx(figures["average"], abs=0.05)  # the paper's rounding


def test_a_table_beside_the_paper_from_a_real_journal():
    lines = lzma.open(ORACLE / "episodes.jsonl.xz", "rt").read().splitlines()[1:]
    # the oracle's episodes, read as a policy's: the table code cannot tell them apart
    records = [{**record, "source": "policy"} for record in map(json.loads, lines) if record.get("source") == "oracle"]
    report = build_report(records, {"seed": 10000, "episodes_per_task": 50})
    oracle, expert = results_table.from_oracle_bench(str(ORACLE / "oracle_bench.json"))
    paper = dict([results_table.load_paper(f"{PAPER}#rvt2")])
    results = results_table.collect({"oracle journal": [report]}, oracle, expert, {}, paper)
    table = results_table.markdown(results).splitlines()
    assert table[0].startswith("| task | oracle journal | paper: rvt2 | oracle journal - paper: rvt2 (points) |")
    assert len(table) == 2 + 18 + 1
    close_jar = next(line for line in table if line.startswith("| close_jar |")).split(" | ")
    rate = report["tasks"]["close_jar"]["policy"]["success_rate"]
    assert close_jar[2] == "100 ± 0" and close_jar[3] == f"{100 * rate - 100:+.0f}"
    assert results["average"]["paper: rvt2"] == pytest.approx(0.8144, abs=1e-4)
    assert results["average"]["oracle journal"] == pytest.approx(
        sum(report["tasks"][t]["policy"]["success_rate"] for t in report["tasks"]) / 18)


def test_an_unknown_model_is_one_line():
    with pytest.raises(SystemExit, match="has no model 'rvt3'; give FILE#MODEL with one of: rvt2, rvt, peract"):
        results_table.load_paper(f"{PAPER}#rvt3")


def test_two_published_ranges_are_one_evaluation_of_100_seeds_per_task():
    """rvt2-18's two ranges of 50 seeds, read from the xz journals kept in benchmarks/results (no eval.json
    there), joined with + into one report whose counts are the journals' own."""
    evals = REPOSITORY / "benchmarks" / "results" / "rvt2_18_h100x4" / "evals"
    ranges = [evals / "seed0_from10000", evals / "seed0_from10050"]
    [report] = results_table.load_models("+".join(map(str, ranges)))
    records = [json.loads(line) for folder in ranges
               for line in lzma.open(folder / "episodes.jsonl.xz", "rt").read().splitlines()[1:]]
    assert report["seed"] == 10000 and report["episodes_per_task"] == 100
    for task in tasks_of_set("rlbench18"):
        mine = [r for r in records if r["task"] == task]
        assert len(mine) == 100 and len({r["seed"] for r in mine}) == 100
        assert report["tasks"][task]["policy"]["successes"] == sum(r["success"] for r in mine)


def test_a_range_of_an_evaluations_seeds_is_read_as_that_range_alone():
    """EVAL_DIR@FIRST-LAST: the second 50 seeds of a 100-seed evaluation, counted as the journal has them."""
    folder = REPOSITORY / "benchmarks" / "results" / "stage2_min_points_h200x2" / "eval_all18_min200"
    [second] = results_table.load_models(f"{folder}@10050-10099")
    records = [json.loads(line) for line in lzma.open(folder / "episodes.jsonl.xz", "rt").read().splitlines()[1:]]
    assert second["seed"] == 10050 and second["episodes_per_task"] == 50
    for task in tasks_of_set("rlbench18"):
        mine = [r for r in records if r["task"] == task and r["seed"] >= 10050]
        assert len(mine) == 50 and second["tasks"][task]["policy"]["successes"] == sum(r["success"] for r in mine)
    with pytest.raises(SystemExit, match="FIRST-LAST"):
        results_table.load_models(f"{folder}@10050")


def test_a_table_without_oracle_and_expert_columns_is_refused_in_one_line(monkeypatch, capsys, tmp_path):
    monkeypatch.setattr("sys.argv", ["results_table", "--policy", f"x={tmp_path}", "--oracle", str(tmp_path)])
    with pytest.raises(SystemExit) as exit_:
        results_table.main()
    assert exit_.value.code == 2
    assert "give the oracle and expert columns" in capsys.readouterr().err


def test_an_evaluation_of_some_tasks_has_rows_for_those_alone():
    """The three-task language pilot (benchmarks/results/rvt2_18_language_h200): rows for its tasks, the
    oracle's rows for them; a column that lacks one of the first column's tasks is one line."""
    evals = REPOSITORY / "benchmarks" / "results" / "rvt2_18_language_h200" / "rvt2_18_language" / "evals"
    [trained] = results_table.load_models(f"{evals / 'seed0'}+{evals / 'seed0_second_range'}")
    oracle, expert = results_table.from_oracle_bench(str(ORACLE / "oracle_bench.json"))
    results = results_table.collect({"trained": [trained]}, oracle, expert, {})
    assert [row["task"] for row in results["rows"]] == ["open_drawer", "push_buttons", "stack_blocks"]
    episodes = {row["task"]: row["policies"]["trained"]["episodes"] for row in results["rows"]}
    assert episodes == {"open_drawer": 100, "push_buttons": 100, "stack_blocks": 50}  # the second range: two tasks
    [second] = results_table.load_models(str(evals / "seed0_second_range"))
    with pytest.raises(SystemExit, match="'second range' has no episodes of stack_blocks"):
        results_table.collect({"trained": [trained], "second range": [second]}, oracle, expert, {})


def test_the_first_phrasing_and_the_others_split_an_evaluation():
    """EVAL_DIR#first: the episodes instructed with their variation's first trained phrasing (the paper's);
    #others the rest. On the published rvt2-18 evaluation the two add up to it, task by task."""
    folder = REPOSITORY / "benchmarks" / "results" / "stage2_min_points_h200x2" / "eval_all18_min200"
    [first], [others], [whole] = (results_table.load_models(f"{folder}{suffix}") for suffix in ("#first", "#others", ""))
    records = [json.loads(line) for line in lzma.open(folder / "episodes.jsonl.xz", "rt").read().splitlines()[1:]]
    for task in tasks_of_set("rlbench18"):
        a, b, c = (r["tasks"][task]["policy"] for r in (first, others, whole))
        assert a["episodes"] + b["episodes"] == c["episodes"] == 100
        assert a["successes"] + b["successes"] == c["successes"]
        template = get_task(task).instructions[0]
        assert a["episodes"] == sum(r["task"] == task and r["instruction"] == template.format(
            **get_task(task).variation_values(r["variation"])) for r in records)
    with pytest.raises(SystemExit, match="first or others"):
        results_table.load_models(f"{folder}#second")


def test_two_evaluations_are_compared_episode_by_episode(tmp_path):
    """--paired: a published journal against itself (no discordant episode), against a copy with some outcomes
    turned over (exactly those counted, and the exact McNemar p of them), and against seeds it does not share."""
    from scipy.stats import binomtest

    folder = REPOSITORY / "benchmarks" / "results" / "rvt2_18_onegpu_3500_h200x2" / "evals" / "seed0_from10000"
    records, seed = results_table.load_records(str(folder))
    assert seed == 10000 and len(records) == 900
    same = results_table.paired(records, records)
    assert (same["episodes"], same["only_first"], same["only_other"], same["p"]) == (900, 0, 0, 1.0)

    header, *lines = lzma.open(folder / "episodes.jsonl.xz", "rt").read().splitlines()
    turned = {"lost": 0, "won": 0}
    copy = []
    for i, line in enumerate(lines):
        record = json.loads(line)
        if record.get("source") == "policy" and i % 7 == 0:  # every seventh episode's outcome turned over
            turned["lost" if record["success"] else "won"] += 1
            record["success"] = not record["success"]
        copy.append(json.dumps(record))
    other = tmp_path / "other"
    other.mkdir()
    (other / "episodes.jsonl").write_text("\n".join([header, *copy]) + "\n")
    against = results_table.paired(records, results_table.load_records(str(other))[0])
    assert against["only_first"] == turned["lost"] > 0 and against["only_other"] == turned["won"] > 0
    assert against["p"] == pytest.approx(binomtest(turned["lost"], turned["lost"] + turned["won"]).pvalue)

    second = folder.parent / "seed0_from10050"
    with pytest.raises(SystemExit, match="share no episode"):
        results_table.paired(records, results_table.load_records(str(second))[0])


def test_a_difference_too_sure_for_a_double_is_printed_as_a_bound():
    """RVT after 850 steps against RVT-2 after 3,500 on the same 1,800 episodes: the exact McNemar p underflows
    to 0 in floating point, and the table says it is below 1e-300 instead of printing a p of 0."""
    def both_ranges(name):
        evals = REPOSITORY / "benchmarks" / "results" / name / "evals"
        return results_table.load_records(f"{evals / 'seed0_from10000'}+{evals / 'seed0_from10050'}")[0]

    against = results_table.paired(both_ranges("rvt_18_onegpu_h200x2"), both_ranges("rvt2_18_onegpu_3500_h200x2"))
    assert against["episodes"] == 1800 and against["only_other"] > 1000 and against["p"] == 0.0
    line = results_table.paired_markdown("RVT", {"RVT-2": against}).splitlines()[-1]
    assert line.endswith("| < 1e-300 |")
    assert results_table.p_value(1.1e-5) == "1.1e-05"
