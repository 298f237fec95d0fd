"""Nothing lost, no tracebacks: every command refuses bad numbers and unusable output paths in one line,
exports never destroy a folder they did not write, damaged checkpoints are named, and training state
loads without running code."""

import json
import os
import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from conftest import assert_one_line_error
from rvt2cli.cli import main

# --- every numeric option checks its range while parsing ------------------------------------------------

OUT_OF_RANGE = [
    ["record", "--task", "push_cube", "--episodes", "0"],
    ["record", "--task", "push_cube", "--episodes", "-1"],
    ["record", "--task", "push_cube", "--workers", "0"],
    ["record", "--task", "push_cube", "--seed", "-1"],
    ["record", "--task", "push_cube", "--image-size", "0"],
    ["record", "--task", "push_cube", "--obs-every", "0"],
    ["record", "--task", "push_cube", "--voxel-size", "0"],
    ["record", "--task", "push_cube", "--max-attempts", "0"],
    ["import-rosbag", "x.mcap", "--obs-every", "0"],
    ["import-rosbag", "x.mcap", "--sync-tolerance", "-0.1"],
    ["import-rosbag", "x.mcap", "--gripper-threshold", "0"],
    ["import-rosbag", "x.mcap", "--scene-bounds", "1,2,3"],
    ["extract-keyframes", "x.mcap", "--stop-velocity", "0"],
    ["extract-keyframes", "x.mcap", "--pause-velocity", "-1"],
    ["extract-keyframes", "x.mcap", "--stop-buffer", "-1"],
    ["extract-keyframes", "x.mcap", "--obs-every", "0"],
    ["extract-keyframes", "x.mcap", "--merge-refinements", "-1"],
    ["render", "x.mcap", "--frame", "-1"],
    ["render", "x.mcap", "--frame", "0", "--image-size", "0"],
    ["pack-samples", "x", "--out", "s.safetensors", "--episodes-per-task", "0"],
    ["train", "--data", "x", "--out", "r", "--steps", "0"],
    ["train", "--data", "x", "--out", "r", "--batch-size", "0"],
    ["train", "--data", "x", "--out", "r", "--lr", "0"],
    ["train", "--data", "x", "--out", "r", "--lr", "nan"],
    ["train", "--data", "x", "--out", "r", "--warmup", "-1"],
    ["train", "--data", "x", "--out", "r", "--max-points", "0"],
    ["train", "--data", "x", "--out", "r", "--seed", "-1"],
    ["train", "--data", "x", "--out", "r", "--save-every", "0"],
    ["train", "--data", "x", "--out", "r", "--val-every", "0"],
    ["train", "--data", "x", "--out", "r", "--log-every", "0"],
    ["train", "--data", "x", "--out", "r", "--val-episodes", "-1"],
    ["train", "--data", "x", "--out", "r", "--episodes-per-task", "0"],
    ["eval", "--checkpoint", "c", "--episodes", "-1"],
    ["eval", "--checkpoint", "c", "--episodes", "0"],
    ["eval", "--checkpoint", "c", "--workers", "0"],
    ["eval", "--checkpoint", "c", "--seed", "-1"],
    ["eval", "--checkpoint", "c", "--keyframe-budget", "0"],
    ["eval", "--checkpoint", "c", "--max-replans", "-1"],
    ["eval", "--checkpoint", "c", "--step-budget-scale", "0"],
    ["eval", "--checkpoint", "c", "--step-budget-scale", "inf"],
    ["eval", "--checkpoint", "c", "--offline", "d", "--batch-size", "0"],
    ["export", "--checkpoint", "c", "--max-points", "0"],
    ["export", "--checkpoint", "c", "--max-points", "many"],
]


@pytest.mark.parametrize("argv", OUT_OF_RANGE, ids=[" ".join(a) for a in OUT_OF_RANGE])
def test_out_of_range_numbers_are_one_line(argv, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "error:" in err[0] and "Traceback" not in err[0], err
    option = next(a for a in argv if a.startswith("--") and argv.index(a) == max(i for i, x in enumerate(argv) if x.startswith("--")))
    assert option in err[0] or "comma-separated" in err[0], err[0]


def test_a_parse_error_is_one_line_from_a_fresh_process(cli):
    assert_one_line_error(cli("eval", "--checkpoint", "c", "--episodes", "-1"), "--episodes", "minimum 1")


# --- output paths that cannot be created ------------------------------------------------------------------

def _blocked(tmp_path: Path) -> Path:
    """A path under a regular file: no one, root included, can create it."""
    (tmp_path / "a_file").write_text("not a folder")
    return tmp_path / "a_file" / "out"


@pytest.mark.sim
def test_unwritable_output_paths_are_one_line(tiny_dataset, tiny_checkpoint, tmp_path, cli):
    run_dir, _ = tiny_checkpoint
    blocked = _blocked(tmp_path)
    episode = sorted(tiny_dataset.glob("*.mcap"))[0]
    runs = {
        "record": ["record", "--task", "push_cube", "--episodes", "1", "--out", blocked],
        "render": ["render", episode, "--frame", "0", "--out", blocked],
        "pack-samples": ["pack-samples", tiny_dataset, "--out", blocked / "s.safetensors"],
        "train": ["train", "--data", tiny_dataset, "--out", blocked, "--config", "small", "--steps", "1"],
        "eval": ["eval", "--checkpoint", run_dir, "--episodes", "1", "--out", blocked],
        "eval --offline": ["eval", "--checkpoint", run_dir, "--offline", tiny_dataset, "--out", blocked],
        "export": ["export", "--checkpoint", run_dir, "--out", blocked],
        "import-rosbag": ["import-rosbag", episode, "--out", blocked, "--task", "t", "--instruction", "i",
                          "--scene-bounds=-1,-1,-1,1,1,1"],
    }
    for name, argv in runs.items():
        r = cli(*argv)
        assert r.returncode == 2, (name, r.stderr[-2000:])
        assert_one_line_error(r, "a_file")
    assert (tmp_path / "a_file").read_text() == "not a folder"


# --- export never empties a folder it did not write --------------------------------------------------------

@pytest.mark.sim
def test_export_refuses_a_folder_that_is_not_a_previous_export(tiny_checkpoint, tmp_path, cli):
    run_dir, _ = tiny_checkpoint
    before = sorted(p.relative_to(run_dir) for p in run_dir.rglob("*"))
    assert_one_line_error(cli("export", "--checkpoint", run_dir, "--out", run_dir), "not a previous export")
    assert sorted(p.relative_to(run_dir) for p in run_dir.rglob("*")) == before  # the run is intact
    mine = tmp_path / "my_folder"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    assert_one_line_error(cli("export", "--checkpoint", run_dir, "--out", mine), "not a previous export")
    assert (mine / "notes.txt").read_text() == "mine"


@pytest.mark.sim
def test_a_previous_export_is_replaced_whole(tiny_checkpoint, onnx_export, tmp_path):
    from rvt2cli.export.exporter import export_policy

    run_dir, _ = tiny_checkpoint
    out = tmp_path / "policy"
    shutil.copytree(onnx_export[1], out)  # a previous ONNX export, then a TorchScript one over it
    export_policy(str(run_dir), "torchscript", str(out), max_points=5000)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["format"] == "torchscript" and (out / "policy.pt").is_file() and not (out / "policy.onnx").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left


# --- damaged checkpoints are named in one line --------------------------------------------------------------

def _copy_checkpoint(run_dir: Path, to: Path) -> Path:
    shutil.copytree(run_dir / (run_dir / "last").read_text().strip(), to)
    return to


@pytest.mark.sim
def test_weights_that_do_not_match_the_config_are_one_line(tiny_checkpoint, tiny_dataset, tmp_path, cli):
    run_dir, _ = tiny_checkpoint
    ckpt = _copy_checkpoint(run_dir, tmp_path / "ckpt")
    weights = load_file(str(ckpt / "model.safetensors"))
    name = next(k for k in weights if weights[k].ndim == 2)
    weights[name] = torch.zeros(weights[name].shape[0] + 1, weights[name].shape[1])
    save_file(weights, str(ckpt / "model.safetensors"))
    for argv in (["eval", "--checkpoint", ckpt, "--episodes", "1", "--out", tmp_path / "e"],
                 ["export", "--checkpoint", ckpt, "--out", tmp_path / "p"]):
        assert_one_line_error(cli(*argv), "model.safetensors", "does not match", "config.json")
    assert not (tmp_path / "p").exists()


@pytest.mark.sim
def test_a_damaged_weights_file_is_one_line(tiny_checkpoint, tmp_path, cli):
    run_dir, _ = tiny_checkpoint
    ckpt = _copy_checkpoint(run_dir, tmp_path / "ckpt")
    data = (ckpt / "model.safetensors").read_bytes()
    (ckpt / "model.safetensors").write_bytes(data[: len(data) // 2])
    assert_one_line_error(cli("export", "--checkpoint", ckpt, "--out", tmp_path / "p"), "model.safetensors", "damaged")
    assert_one_line_error(cli("eval", "--checkpoint", ckpt, "--offline", ckpt), "model.safetensors", "damaged")


# --- training state loads without running code --------------------------------------------------------------

class _Payload:
    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.mark.sim
def test_a_training_state_that_would_run_code_is_refused(tiny_checkpoint, tiny_dataset, tmp_path, cli):
    run_dir, _ = tiny_checkpoint
    run = tmp_path / "run"
    _copy_checkpoint(run_dir, run / "checkpoints" / "step_0000300")
    (run / "last").write_text("checkpoints/step_0000300\n")
    marker = tmp_path / "pwned"
    torch.save({"step": _Payload(str(marker))}, run / "checkpoints" / "step_0000300" / "training_state.pt")
    r = cli("train", "--out", run, "--resume")
    assert_one_line_error(r, "training_state.pt", "not a training state rvt2 can load safely")
    assert not marker.exists()


# --- files others can read -------------------------------------------------------------------------------------

def _modes(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mode & 0o777 for p in folder.rglob("*") if p.is_file()}


@pytest.mark.sim
def test_outputs_have_the_permissions_a_plain_open_gives(tiny_checkpoint, tiny_dataset, tmp_path):
    """safetensors writes its files 0600; every output still ends as readable as the files beside it
    (a policy folder copied to a robot is run by another user)."""
    from rvt2cli.atomic import current_umask
    from rvt2cli.export.exporter import export_policy
    from rvt2cli.train.sample_cache import pack_sample_cache

    run_dir, _ = tiny_checkpoint
    checkpoint = _modes(run_dir / (run_dir / "last").read_text().strip())
    assert set(checkpoint.values()) == {0o666 & ~current_umask()}, checkpoint
    assert {"model.safetensors", "instructions.safetensors"} <= set(checkpoint)

    before = os.umask(0o027)  # a umask other than the usual 022: the modes follow it
    try:
        assert current_umask() == 0o027
        cache = tmp_path / "samples.safetensors"
        pack_sample_cache([str(tiny_dataset)], cache, progress=False)
        export_policy(str(run_dir), "torchscript", str(tmp_path / "policy"), max_points=5000)
    finally:
        os.umask(before)
    assert cache.stat().st_mode & 0o777 == 0o640
    policy = _modes(tmp_path / "policy")
    assert set(policy.values()) == {0o640}, policy
    assert "instructions.safetensors" in policy
