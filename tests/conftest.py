import os
import subprocess
import sys
from dataclasses import dataclass

import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")


@dataclass
class CliResult:
    returncode: int
    stdout: str
    stderr: str


def run_cli(*args: str, timeout: float = 600) -> CliResult:
    """Run `rvt2 ...` in a fresh process, as a user would."""
    p = subprocess.run([sys.executable, "-m", "rvt2cli", *map(str, args)], capture_output=True, text=True, timeout=timeout)
    return CliResult(p.returncode, p.stdout, p.stderr)


def assert_one_line_error(result: CliResult, *fragments: str) -> None:
    """A user error: exit code 2, exactly one line on stderr naming the problem, no traceback."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


@pytest.fixture
def cli():
    return run_cli


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """Two real stack_cube demos (three cameras at 64 px), with the keyframes `rvt2 record` writes into them: the
    data of the train, eval and export tests."""
    from rvt2cli.record.recorder import RecordOptions, record

    out = tmp_path_factory.mktemp("tiny_dataset")
    summary = record("stack_cube", 2, out, seed=0,
                     options=RecordOptions(cameras=("front", "left_shoulder", "right_shoulder"), image_size=64))
    assert len(summary.successes) == 2
    return out


TINY_TRAIN = dict(config="small", batch_size=8, lr=3e-3, warmup=10, augment=False, val_episodes=0, max_points=20000,
                  progress=False)


@pytest.fixture(scope="session")
def tiny_checkpoint(tiny_dataset, tmp_path_factory):
    """The small config trained to overfit the tiny dataset (about a minute on 2 cores)."""
    from rvt2cli.train.trainer import TrainOptions, train

    out = tmp_path_factory.mktemp("runs") / "tiny"
    result = train(TrainOptions(data=[str(tiny_dataset)], out=str(out), steps=300, save_every=150, **TINY_TRAIN), say=lambda *_: None)
    return out, result


AIM = [0.1, 0.0, 0.03]  # stack_cube's aim offset in `aimed_checkpoint` (as `--aim-held` would keep it)


@pytest.fixture(scope="session")
def aimed_checkpoint(tiny_checkpoint, tmp_path_factory):
    """The tiny checkpoint as if trained with `--aim-held` and an aim offset for stack_cube (its config
    says so; the weights are the same)."""
    import json
    import shutil

    from rvt2cli.train.checkpoint import resolve

    aimed = tmp_path_factory.mktemp("aimed") / "checkpoint"
    shutil.copytree(resolve(tiny_checkpoint[0]), aimed)
    config = json.loads((aimed / "config.json").read_text())
    (aimed / "config.json").write_text(json.dumps({**config, "aim_offsets": {"stack_cube": AIM}}))
    return aimed


@pytest.fixture(scope="session")
def onnx_export(aimed_checkpoint, tiny_dataset, tmp_path_factory):
    """`rvt2 export --format onnx` of the aimed checkpoint, parity-checked on the tiny dataset, in a fresh
    process where the export is the first thing traced: (the command's result, the exported folder).
    Made once, since the ONNX exporter takes over a minute on 2 cores; the tests only read the folder."""
    out = tmp_path_factory.mktemp("onnx_export") / "policy"
    result = run_cli("export", "--checkpoint", aimed_checkpoint, "--format", "onnx", "--out", out,
                     "--max-points", "20000", "--check-data", tiny_dataset)
    return result, out
