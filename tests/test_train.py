"""`rvt2 train` on real recorded demos: it learns, it resumes exactly, and it refuses bad input."""

import csv
import json
import re

import pytest
import torch

from conftest import TINY_TRAIN, assert_one_line_error
from rvt2cli.cli import build_parser
from rvt2cli.cli.train import options_from
from rvt2cli.errors import UserError
from rvt2cli.model.config import STAGE2_MIN_POINTS
from rvt2cli.train.checkpoint import load_checkpoint, load_policy
from rvt2cli.train.metrics import prediction_errors
from rvt2cli.train.run_folder import model_config
from rvt2cli.train.trainer import TrainOptions, train

pytestmark = pytest.mark.sim


def test_small_config_overfits_tiny_dataset(tiny_checkpoint):
    run_dir, result = tiny_checkpoint
    assert result.steps == 300 and result.skipped_steps == 0
    assert sum(result.losses[-10:]) / 10 < 0.5 * result.losses[0]
    policy, ckpt = load_policy(run_dir)
    errors = prediction_errors(policy, result.packed)
    assert errors["translation_mm"] < 10.0, errors  # below 1 cm on the training samples
    assert errors["gripper_accuracy"] >= 0.9
    assert ckpt.info["tasks"] == ["stack_cube"] and ckpt.info["step"] == 300


def test_run_folder_layout(tiny_checkpoint):
    run_dir, _ = tiny_checkpoint
    assert (run_dir / "last").read_text().strip() == "checkpoints/step_0000300"
    ckpt_dir = run_dir / "checkpoints" / "step_0000300"
    for name in ("config.json", "model.safetensors", "instructions.safetensors", "training_state.pt"):
        assert (ckpt_dir / name).is_file()
    config = json.loads((ckpt_dir / "config.json").read_text())
    assert config["model"]["name"] == "small" and config["instructions"]
    rows = list(csv.DictReader(open(run_dir / "train.csv")))
    assert [int(r["step"]) for r in rows][-1] == 300 and float(rows[-1]["samples_per_s"]) > 0
    assert any((run_dir / "tb").iterdir())
    assert (run_dir / "checkpoints" / "step_0000150").is_dir()


def test_resume_reproduces_the_same_losses(tiny_dataset, tmp_path):
    opts = dict(data=[str(tiny_dataset)], steps=6, save_every=3, **TINY_TRAIN)
    straight = train(TrainOptions(out=str(tmp_path / "a"), **opts), say=lambda *_: None)
    first = train(TrainOptions(out=str(tmp_path / "b"), **{**opts, "steps": 3}), say=lambda *_: None)
    # a run of 3 steps has its cosine schedule end at step 3: resume a copy of the 6-step run instead
    (tmp_path / "c").mkdir()
    import shutil

    copy = tmp_path / "c" / "checkpoints" / "step_0000003"
    shutil.copytree(tmp_path / "a" / "checkpoints" / "step_0000003", copy)
    (tmp_path / "c" / "last").write_text("checkpoints/step_0000003\n")
    # as a checkpoint written before `stage2_min_points` existed: the resumed run keeps that older behaviour
    config = json.loads((copy / "config.json").read_text())
    del config["model"]["stage2_min_points"], config["options"]["stage2_min_points"]
    (copy / "config.json").write_text(json.dumps(config))
    resumed = train(TrainOptions(out=str(tmp_path / "c"), resume=True, **opts), say=lambda *_: None)
    assert first.losses == straight.losses[:3]
    assert resumed.losses == straight.losses[3:]
    a, c = load_checkpoint(tmp_path / "a"), load_checkpoint(tmp_path / "c")
    assert all(torch.equal(a.weights[k], c.weights[k]) for k in a.weights)
    assert a.config.stage2_min_points == STAGE2_MIN_POINTS and c.config.stage2_min_points == 0


def test_a_time_limit_saves_and_stops_and_resume_finishes_the_same_run(tiny_dataset, tmp_path, cli):
    """--time-limit stops at the first look after the limit (here every 3 steps, the limit already past), with a
    checkpoint there although --save-every is 6; --resume, without the limit, ends as the run that never
    stopped: the same losses and weights. The command says how to continue and exits 75."""
    opts = dict(data=[str(tiny_dataset)], steps=6, save_every=6, log_every=3, **TINY_TRAIN)
    straight = train(TrainOptions(out=str(tmp_path / "a"), **opts), say=lambda *_: None)
    said = []
    stopped = train(TrainOptions(out=str(tmp_path / "b"), time_limit=1e-9, **opts), say=said.append)
    assert stopped.out_of_time and stopped.steps == 3
    run = json.loads((tmp_path / "b" / "run.json").read_text())
    assert run["out_of_time"] is True
    # where the time before the first step went: the data line, and run.json's setup_seconds within seconds
    assert 0 < run["setup_seconds"] < run["seconds"]
    assert any(line.startswith("data: ") and "read and embedded in" in line and "packed in" in line for line in said)
    assert (tmp_path / "b" / "last").read_text().strip() == "checkpoints/step_0000003"
    assert any("--resume" in line for line in said)
    resumed = train(TrainOptions(out=str(tmp_path / "b"), resume=True, **opts), say=lambda *_: None)
    assert not resumed.out_of_time and resumed.steps == 6
    assert stopped.losses + resumed.losses == straight.losses
    a, b = load_checkpoint(tmp_path / "a").weights, load_checkpoint(tmp_path / "b").weights
    assert all(torch.equal(a[k], b[k]) for k in a)

    r = cli("train", "--data", tiny_dataset, "--out", tmp_path / "c", "--config", "small", "--steps", "4",
            "--log-every", "2", "--val-episodes", "0", "--max-points", "20000", "--time-limit", "1e-9", "--no-progress")
    assert r.returncode == 75, r.stderr[-2000:]
    assert f"Continue with: rvt2 train --out {tmp_path / 'c'} --resume" in r.stdout
    resume = build_parser().parse_args(["train", "--out", str(tmp_path / "c"), "--resume"])
    assert options_from(resume).time_limit is None   # the limit was the command's, not the run's


def test_stage2_min_points_is_the_configs_unless_the_run_sets_it():
    """`rvt2 train --stage2-min-points N` goes into the checkpoint's model config (an inference setting);
    without it, the named config's; a one-stage config has no stage 2 to set it for."""
    def config(*flags):
        return model_config(options_from(build_parser().parse_args(["train", "--data", "d", "--out", "o", *flags])))

    assert config().stage2_min_points == config("--config", "small").stage2_min_points == STAGE2_MIN_POINTS > 0
    assert config("--stage2-min-points", "0").stage2_min_points == 0
    assert config("--stage2-min-points", "50").network() == config().network()  # the same network to train
    with pytest.raises(UserError, match="one stage.*--stage2-min-points"):
        config("--config", "rvt", "--stage2-min-points", "50")


def test_resume_with_another_config_is_refused(tiny_checkpoint, tiny_dataset):
    run_dir, _ = tiny_checkpoint
    with pytest.raises(UserError, match=r"--config 'rvt' differs from the run's 'small'.*keeps its options"):
        train(TrainOptions(data=[str(tiny_dataset)], out=str(run_dir), resume=True, config="rvt", steps=301))


def test_training_into_an_existing_run_needs_resume(tiny_checkpoint, tiny_dataset, cli):
    run_dir, _ = tiny_checkpoint
    r = cli("train", "--data", tiny_dataset, "--out", run_dir, "--config", "small", "--steps", "1")
    assert_one_line_error(r, "already holds a run", "--resume")


def _tree(folder) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_run_stopped_before_its_first_checkpoint_is_started_again_not_resumed(tiny_dataset, tmp_path, cli):
    run = tmp_path / "run"
    train(TrainOptions(data=[str(tiny_dataset)], out=str(run), steps=1, **TINY_TRAIN), say=lambda *_: None)
    # what a run killed before its first save leaves: its logs and run.json, no checkpoint
    import shutil

    shutil.rmtree(run / "checkpoints")
    (run / "last").unlink()
    before = _tree(run)
    assert_one_line_error(cli("train", "--out", run, "--resume"), str(run), "no checkpoint yet", "without --resume")
    assert _tree(run) == before
    again = train(TrainOptions(data=[str(tiny_dataset)], out=str(run), steps=1, **TINY_TRAIN), say=lambda *_: None)
    assert again.steps == 1 and (run / "last").is_file()


def test_training_refuses_a_folder_with_files_of_its_own(tiny_dataset, tmp_path, cli):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    for resume in ([], ["--resume"]):
        r = cli("train", "--data", tiny_dataset, "--out", mine, "--config", "small", "--steps", "1", *resume)
        assert_one_line_error(r, str(mine), "not an rvt2 run folder", "notes.txt")
    assert _tree(mine) == {"notes.txt": b"mine"}


def test_data_without_keyframes_is_refused(tmp_path, cli):
    from rvt2cli.record.recorder import RecordOptions, record

    record("push_cube", 1, tmp_path, options=RecordOptions(cameras=("front",), image_size=32, keyframes=False))
    r = cli("train", "--data", tmp_path, "--out", tmp_path / "run", "--config", "small")
    assert_one_line_error(r, "push_cube_0000.mcap", "no keyframes", "rvt2 extract-keyframes")


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without a GPU")
def test_cuda_without_gpu_is_a_clear_error(tiny_dataset, tmp_path, cli):
    r = cli("train", "--data", tiny_dataset, "--out", tmp_path / "run", "--config", "small", "--device", "cuda")
    assert_one_line_error(r, "--device cuda", "no CUDA GPU", "--device cpu")


def test_non_finite_steps_are_skipped_then_training_stops(tiny_dataset, tmp_path):
    # an absurd learning rate blows the weights up within a step or two; every later step is non-finite
    opts = TrainOptions(data=[str(tiny_dataset)], out=str(tmp_path / "run"), steps=50, max_bad_steps=3,
                        **{**TINY_TRAIN, "lr": 1e30})
    with pytest.raises(UserError, match=r"training diverged: 4 steps with a non-finite loss or gradient") as raised:
        train(opts, say=lambda *_: None)
    # the line says what was not finite, each term with its count of skipped steps, then what to try
    message = str(raised.value)
    terms = re.search(r"not finite: (.*)\); lower --lr or check the data$", message)
    assert terms, message
    counts = {name: int(n) for name, n in
              (re.fullmatch(r"(.+) in (\d+) steps?", part).groups() for part in terms.group(1).split(", "))}
    assert set(counts) <= {"heatmap1", "heatmap2", "rot_x", "rot_y", "rot_z", "gripper", "collision",
                           "gradient only"}, counts
    assert counts and all(1 <= n <= 4 for n in counts.values()), counts


def test_torchrun_trains_with_two_processes(tiny_dataset, tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    torchrun = Path(sys.executable).parent / "torchrun"
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run([str(torchrun), "--nproc-per-node", "2", "-m", "rvt2cli", "train", "--data", str(tiny_dataset),
                        "--out", str(out), "--config", "small", "--steps", "3", "--batch-size", "2", "--max-points", "5000",
                        "--val-episodes", "0", "--no-progress"], capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "batch 2 x 2" in r.stdout  # two ranks, one log
    assert r.stdout.count("trained 3 steps") == 1 and r.stdout.count("data: ") == 1, r.stdout
    assert load_checkpoint(out).info["step"] == 3


_SHARED_DATA_CHECK = """
import dataclasses
import sys
import torch
from rvt2cli.train.data_sharing import load_data
from rvt2cli.train.run_folder import model_config
from rvt2cli.train.trainer import TrainOptions
from rvt2cli.train.training_data import read_data
from rvt2cli.train.training_state import init_distributed

rank, world = init_distributed()
opts = TrainOptions(data=[sys.argv[1]], out=sys.argv[2], config="small", max_points=3000, val_episodes=1, progress=False,
                    phrasings="all")
cfg = model_config(opts)
shared = load_data(opts, cfg, torch.device("cpu"), False, None, lambda *_: None)
own = read_data(opts, cfg, torch.device("cpu"), False, None, lambda *_: None)
assert (shared.packed_val is None) == (own.packed_val is None)
for a, b in ((shared.packed, own.packed), (shared.packed_val, own.packed_val)):
    for name in [f.name for f in dataclasses.fields(a)] if a is not None else []:
        value, other = getattr(a, name), getattr(b, name)
        same = torch.equal(value, other) if torch.is_tensor(value) else (value == other).all() if hasattr(value, "all") else value == other
        assert same, (rank, name)
assert shared.selected == own.selected and shared.samples.episodes == own.samples.episodes
assert shared.packed.phrasings is not None and int(shared.packed.phrasing_count.max()) == 3  # stack_cube's templates
assert shared.instructions.as_dict().keys() == own.instructions.as_dict().keys()
assert not shared.samples.xyz and not own.samples.xyz  # the clouds as read are dropped once packed
print(f"rank {rank} of {world}: the same {len(shared.packed)} samples")
"""


def test_several_processes_train_on_the_data_process_0_read(tiny_dataset, tmp_path, cli):
    """In a several-process run one process reads the episodes; the others receive exactly what reading
    them gives (packed clouds, targets, split, instructions and their phrasings). Data that cannot be trained on stops every
    process with the one-line error, instead of leaving the others waiting."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from rvt2cli.record.recorder import RecordOptions, record

    torchrun = Path(sys.executable).parent / "torchrun"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    script = tmp_path / "check.py"
    script.write_text(_SHARED_DATA_CHECK)
    r = subprocess.run([str(torchrun), "--nproc-per-node", "2", str(script), str(tiny_dataset), str(tmp_path / "run")],
                       capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "rank 0 of 2: the same" in r.stdout and "rank 1 of 2: the same" in r.stdout

    unannotated = tmp_path / "unannotated"
    record("push_cube", 1, unannotated, options=RecordOptions(cameras=("front",), image_size=32, keyframes=False))
    r = subprocess.run([str(torchrun), "--nproc-per-node", "2", "-m", "rvt2cli", "train", "--data", str(unannotated),
                        "--out", str(tmp_path / "bad"), "--config", "small", "--no-progress"],
                       capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode != 0 and r.stderr.count("no keyframes; run `rvt2 extract-keyframes") == 2, r.stderr[-3000:]
    assert "Traceback" not in r.stderr.split("no keyframes")[0]



def test_share_bench_sends_the_data_with_its_instruction_embeddings_at_their_own_size(tmp_path):
    """benchmarks/share_bench.py on two CPU processes: every process ends with the first one's data, and the
    pickled instruction embeddings weigh what the embeddings do (a view per instruction into one batch once
    pickled that batch per instruction: 36.8 GiB for rvt2-18, past a GPU's free memory)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from benchmarks.share_bench import LANG_DIM, LANG_TOKENS

    out = tmp_path / "share.json"
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", "-m",
                        "benchmarks.share_bench", "--scale", "0.02", "--json", str(out)],
                       cwd=Path(__file__).parent.parent, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(out.read_text())
    assert result["same"] and len(result["processes"]) == 2
    embeddings_mib = 11 * LANG_TOKENS * LANG_DIM * 4 / 2**20   # int(578 * 0.02) instructions
    assert result["instruction_cache_mib"] < 1.1 * embeddings_mib

def _two_nodes(out, *extra) -> list[list[str]]:
    """`rvt2 train` as two machines start it (README, "Several machines"): one torchrun per node, one
    process each, meeting at a c10d rendezvous; here both nodes are this machine."""
    import socket
    import sys
    from pathlib import Path

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    torchrun = Path(sys.executable).parent / "torchrun"
    node = [str(torchrun), "--nnodes", "2", "--nproc-per-node", "1", "--rdzv-backend", "c10d",
            "--rdzv-endpoint", f"127.0.0.1:{port}", "--rdzv-id", f"rvt2-{port}",
            "-m", "rvt2cli", "train", "--out", str(out), *extra]
    return [node, node]


def _run_nodes(commands, env, timeout=900) -> None:
    import subprocess

    procs = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for c in commands]
    for p in procs:
        _, err = p.communicate(timeout=timeout)
        assert p.returncode == 0, err[-3000:]


def test_two_node_run_killed_and_resumed_continues_exactly_on_both_ranks(tiny_dataset, tmp_path):
    """Two "nodes" of one gloo process each (torchrun --nnodes 2, c10d rendezvous), killed after their
    first checkpoint and resumed with only --resume: the result equals an uninterrupted run, each rank
    kept its own sampling state, and rank 0 alone wrote the run's files (each log row once)."""
    import os
    import signal
    import subprocess
    import time

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    common = ["--data", str(tiny_dataset), "--config", "small", "--steps", "16", "--batch-size", "2", "--max-points", "3000",
              "--val-episodes", "0", "--save-every", "4", "--log-every", "1", "--warmup", "2", "--lr", "3e-3", "--no-progress"]
    _run_nodes(_two_nodes(tmp_path / "a", *common), env)

    run = tmp_path / "b"
    procs = [subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, start_new_session=True)
             for c in _two_nodes(run, *common)]
    deadline = time.time() + 600
    while not (run / "last").exists() and time.time() < deadline and all(p.poll() is None for p in procs):
        time.sleep(0.05)
    for p in procs:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    killed_at = load_checkpoint(run).info["step"]
    assert killed_at < 16
    state = load_checkpoint(run).state()
    assert state["world_size"] == 2 and not torch.equal(state["generators"][0], state["generators"][1])

    _run_nodes(_two_nodes(run, "--resume"), env)
    a, b = load_checkpoint(tmp_path / "a"), load_checkpoint(run)
    assert b.info["step"] == 16 and all(torch.equal(a.weights[k], b.weights[k]) for k in a.weights)
    rows = lambda d: [(r["step"], r["loss"]) for r in csv.DictReader(open(d / "train.csv"))]  # noqa: E731
    assert rows(run) == rows(tmp_path / "a") and [s for s, _ in rows(run)] == [str(s) for s in range(1, 17)]

    from benchmarks.ddp_bench import compare_losses  # the loss-curve comparison of docs/BENCHMARKS.md

    same = compare_losses(tmp_path / "a", run, window=4)
    assert same["steps_compared"] == 16 and same["max_gap"] == 0.0 and same["row_noise"]["one_gpu"] > 0


def test_resume_keeps_the_runs_options_and_refuses_a_changed_one(tiny_checkpoint, cli):
    run_dir, _ = tiny_checkpoint
    r = cli("train", "--out", run_dir, "--resume", "--steps", "400", "--lr", "1e-3")
    assert_one_line_error(r, "--steps 400", "differs from the run's 300", "keeps its options")
    r = cli("train", "--out", run_dir, "--resume", "--no-progress")  # the stored options: already at its last step
    assert r.returncode == 0, r.stderr[-2000:]
    assert "trained 300 steps" in r.stdout


@pytest.mark.slow
def test_compiled_training_compiles_its_graphs_once(tiny_dataset, tmp_path):
    """`rvt2 train --compile` compiles the network, once, at the training batch: counting FLOPs on one
    sample and validating at other batch sizes run eagerly. (Counting FLOPs in torch's FlopCounterMode on
    the compiled network made torch skip compiling it for good: rvt2 train --compile trained eagerly,
    512 samples/s instead of 723 on an H200.)"""
    import torch._dynamo
    from torch._dynamo.utils import counters

    from rvt2cli.model.config import get_config
    from rvt2cli.model.policy import RVT2Policy
    from rvt2cli.train.batches import BatchStream
    from rvt2cli.train.data_sharing import load_data

    torch._dynamo.reset()
    counters.clear()
    with torch._dynamo.config.patch(error_on_recompile=True):
        train(TrainOptions(data=[str(tiny_dataset)], out=str(tmp_path / "run"), steps=2, save_every=2, compile=True,
                           **TINY_TRAIN), say=lambda *_: None)
        assert counters["frames"]["ok"] >= 2, dict(counters["frames"])  # both stages were compiled, not skipped
        torch._dynamo.reset()
        cfg = get_config("small")
        opts = TrainOptions(data=[str(tiny_dataset)], out=str(tmp_path / "x"), **TINY_TRAIN)
        packed = load_data(opts, cfg, torch.device("cpu"), False, None, lambda *_: None).packed
        policy = RVT2Policy(cfg, render_backend="torch")
        policy.compile_network()
        batch = next(BatchStream(packed, cfg, torch.Generator().manual_seed(0), 4))
        for _ in range(2):
            policy(batch.obs, batch.position, batch.rot_bins, batch.stage2_center)
            with policy.eager():  # validation-sized batches: no compilation at all
                one = next(BatchStream(packed, cfg, torch.Generator().manual_seed(1), 1))
                policy(one.obs, one.position, one.rot_bins, one.stage2_center)
                policy.predict(one.obs)


def test_loop_bench_times_the_command_beside_its_step(tiny_dataset, tmp_path):
    """benchmarks/loop_bench.py --quick: rvt2 train's own rate next to the step on synthetic and real batches."""
    import subprocess
    import sys
    from pathlib import Path

    out = tmp_path / "loop.json"
    root = Path(__file__).parent.parent
    r = subprocess.run([sys.executable, "-m", "benchmarks.loop_bench", "--data", str(tiny_dataset), "--quick", "--json", str(out)],
                       cwd=root, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    variants = json.loads(out.read_text())["variants"]
    assert {"rvt2 train", "synthetic", "real", "loop", "batch_only"} <= set(variants)
    assert all(v["samples_per_s"] > 0 for k, v in variants.items() if k != "batch_only")


def test_rotation_bins_set_the_policys_rotation_resolution(tiny_dataset, tmp_path, cli):
    """--rotation-bins 360 --rotation-sigma 2: the heads score 1-degree bins against soft targets, the
    checkpoint keeps both, a resumed run may not change them."""
    from rvt2cli.model.rotation import angle_between, bins_to_quaternion, quaternion_to_bins

    run_dir = tmp_path / "fine"
    train(TrainOptions(data=[str(tiny_dataset)], out=str(run_dir), steps=2, save_every=2, rotation_bins=360,
                       rotation_sigma=2.0, **TINY_TRAIN), say=lambda *_: None)
    policy, ckpt = load_policy(run_dir)
    assert ckpt.config.rotation_bins == 360 and policy.cfg.rotation_bins == 360
    assert ckpt.config.rotation_sigma_deg == policy.cfg.rotation_sigma_deg == 2.0   # soft targets, decoded over 4 bins
    head = next(m for m in policy.modules() if hasattr(m, "rot_z"))
    assert head.rot_x.out_features == head.rot_z.out_features == 360
    quaternion = torch.nn.functional.normalize(torch.tensor([0.1, 0.7, 0.2, 0.6]), dim=0).numpy()
    centre = bins_to_quaternion(quaternion_to_bins(quaternion, 360), 360)
    coarse = bins_to_quaternion(quaternion_to_bins(quaternion, 72), 72)
    assert angle_between(centre[None], quaternion[None])[0] < angle_between(coarse[None], quaternion[None])[0]
    assert angle_between(centre[None], quaternion[None])[0] <= 0.5 * 3 ** 0.5 + 1e-6  # half a degree per axis at most
    r = cli("train", "--data", tiny_dataset, "--out", run_dir, "--resume", "--rotation-bins", "72", "--steps", "4")
    assert_one_line_error(r, "--rotation-bins 72 differs from the run's 360")
    r = cli("train", "--data", tiny_dataset, "--out", tmp_path / "bad", "--config", "small", "--rotation-bins", "2")
    assert r.returncode != 0 and "below the minimum 4" in r.stderr


def test_start_share_draws_keyframe_starts_and_is_kept_with_the_run(tiny_dataset, tmp_path, cli):
    """--start-share 0.5: half of each task's draws come from its keyframe-start samples (the only
    observations a closed loop makes), the other half from all samples as before; 0 draws exactly what
    the plain sampler draws; the run keeps the share, and a resume may not change it."""
    import numpy as np

    from rvt2cli.model.config import get_config
    from rvt2cli.train.batches import TaskSampler
    from rvt2cli.train.data_sharing import load_data

    opts = TrainOptions(data=[str(tiny_dataset)], out=str(tmp_path / "x"), **TINY_TRAIN)
    packed = load_data(opts, get_config("small"), torch.device("cpu"), False, None, lambda *_: None).packed
    start = packed.keyframe_start
    assert 0 < start.sum() < len(start)
    draws = TaskSampler(packed.task, start, 0.5).sample(20_000, torch.Generator().manual_seed(0))
    expected = 0.5 + 0.5 * start.mean()   # the uniform half also lands on a start now and then
    assert abs(start[draws].mean() - expected) < 0.02
    assert set(draws[start[draws]]) == set(np.flatnonzero(start))   # every start sample is drawn
    plain = TaskSampler(packed.task).sample(500, torch.Generator().manual_seed(3))
    assert (TaskSampler(packed.task, start, 0.0).sample(500, torch.Generator().manual_seed(3)) == plain).all()
    assert start[TaskSampler(packed.task, start, 1.0).sample(500, torch.Generator().manual_seed(3))].all()

    run_dir = tmp_path / "share"
    said = []
    train(TrainOptions(data=[str(tiny_dataset)], out=str(run_dir), steps=2, save_every=2, start_share=0.5,
                       task_weights={"stack_cube": 2.0}, **TINY_TRAIN), say=said.append)
    assert "task shares of the draws (--task-weights): stack_cube 100%" in said
    stored = json.loads((run_dir / "run.json").read_text())["options"]
    assert stored["start_share"] == 0.5 and stored["task_weights"] == {"stack_cube": 2.0}
    r = cli("train", "--out", run_dir, "--resume", "--start-share", "0.2")
    assert_one_line_error(r, "--start-share 0.2 differs from the run's 0.5")
    r = cli("train", "--out", run_dir, "--resume", "--task-weights", "stack_cube=3")
    assert_one_line_error(r, "--task-weights {'stack_cube': 3.0} differs from the run's {'stack_cube': 2.0}")
    r = cli("train", "--data", tiny_dataset, "--out", tmp_path / "bad", "--start-share", "1.5")
    assert r.returncode != 0 and "1.5" in r.stderr
    r = cli("train", "--data", tiny_dataset, "--out", tmp_path / "bad", "--task-weights", "insert_peg=3,stack_cube=1",
            "--no-progress")
    assert_one_line_error(r, "--task-weights: no insert_peg in --data (its tasks: stack_cube)")
    assert not (tmp_path / "bad").exists()
    r = cli("train", "--data", tiny_dataset, "--out", tmp_path / "bad", "--task-weights", "insert_peg=0")
    assert r.returncode == 2 and "'insert_peg=0' is not NAME=WEIGHT with a positive weight" in r.stderr


def test_task_weights_set_each_task_share_of_the_draws():
    """--task-weights: a task's share of the draws is its weight over the sum (here 3:1:1), over the
    tasks the training split holds (a task with no samples draws nothing); without weights the sampler
    draws the uniform random numbers it always did."""
    import numpy as np

    from rvt2cli.train.batches import TaskSampler

    task = np.repeat([0, 1, 2], [50, 10, 40])
    draws = TaskSampler(task, task_weights=np.array([3.0, 1.0, 1.0])).sample(20_000, torch.Generator().manual_seed(0))
    assert np.allclose(np.bincount(task[draws], minlength=3) / 20_000, [0.6, 0.2, 0.2], atol=0.015)
    assert np.allclose(TaskSampler(task, task_weights=np.array([3.0, 1.0, 1.0])).shares(), [0.6, 0.2, 0.2])
    without_1 = np.repeat([0, 2], [30, 30])
    sampler = TaskSampler(without_1, task_weights=np.array([3.0, 1.0, 1.0]))
    assert np.allclose(sampler.shares(), [0.75, 0.25])
    assert np.allclose(np.mean(without_1[sampler.sample(20_000, torch.Generator().manual_seed(1))] == 0), 0.75, atol=0.015)
    generator = torch.Generator().manual_seed(4)
    expected_tasks = torch.randint(3, (200,), generator=generator).numpy()
    uniform = TaskSampler(task).sample(200, torch.Generator().manual_seed(4))
    assert (task[uniform] == expected_tasks).all()


def test_zoom_and_coarse_action_features_are_kept_with_the_run(tiny_dataset, tmp_path, cli):
    """--zoom and --coarse-action-features change the network: the checkpoint's config carries them (so
    eval, the offline score and export build the same network), a resume may not change them, and a
    one-stage config refuses them."""
    run_dir = tmp_path / "coarse"
    train(TrainOptions(data=[str(tiny_dataset)], out=str(run_dir), steps=2, save_every=2, zoom=2.0,
                       coarse_action_features=True, **TINY_TRAIN), say=lambda *_: None)
    policy, ckpt = load_policy(run_dir)   # loads every weight of the wider action head
    assert ckpt.config.zoom == 2.0 and ckpt.config.coarse_action_features and policy.action.reads_coarse
    assert_one_line_error(cli("train", "--out", run_dir, "--resume", "--zoom", "4"), "--zoom 4.0 differs from the run's 2.0")
    one_stage = cli("train", "--data", tiny_dataset, "--out", tmp_path / "rvt", "--config", "rvt", "--coarse-action-features")
    assert_one_line_error(one_stage, "--config rvt has one stage")
    assert not (tmp_path / "rvt").exists()


def test_packed_clouds_are_each_cloud_fitted_as_one_observation_is(tiny_dataset):
    """pack writes each recorded cloud into its zeroed row (`copy_points_into`); the rows are what
    `fit_points`, the single observation's path (deploy, export), makes of the same cloud with the same
    random stream: subsampled in order where the cloud is larger than max_points, zero-padded where smaller;
    and the same however many threads copy them."""
    import numpy as np

    from rvt2cli.data.paths import episode_paths
    from rvt2cli.model.config import SMALL
    from rvt2cli.model.observation import fit_points
    from rvt2cli.train.packed import fit_clouds, pack
    from rvt2cli.train.samples import load_samples

    samples = load_samples(episode_paths([str(tiny_dataset)]), progress=False)
    lang = torch.zeros(len(samples.instructions), SMALL.lang_tokens, 384)
    sizes = sorted(len(x) for x in samples.xyz)
    max_points = sizes[len(sizes) // 2]  # half the clouds are subsampled, half padded
    indices = list(range(len(samples)))[::-1]
    packed = pack(samples, indices, lang, max_points, "cpu", seed=3)
    rng = np.random.default_rng(3)
    subsampled = 0
    for row, i in enumerate(indices):
        xyz, rgb, count = fit_points(samples.xyz[i], samples.rgb[i], max_points, rng)
        subsampled += len(samples.xyz[i]) > max_points
        assert packed.count[row] == count == min(len(samples.xyz[i]), max_points)
        assert np.array_equal(packed.xyz[row].numpy(), xyz) and np.array_equal(packed.rgb[row].numpy(), rgb)
    assert 0 < subsampled < len(indices)
    for threads in (1, 3):   # the rows are copied in threads; the subsets come from the one stream, in row order
        xyz, rgb, count = fit_clouds(samples, indices, max_points, np.random.default_rng(3), threads=threads)
        assert np.array_equal(xyz, packed.xyz.numpy()) and np.array_equal(rgb, packed.rgb.numpy())
        assert np.array_equal(count, packed.count.numpy())


def test_an_aim_offset_moves_the_held_targets_and_keeps_the_tcp_for_scoring(tiny_dataset):
    """With aim offsets, a sample observed with the gripper closed targets the aimed point, rigidly ahead
    of the TCP's target (augmented alike); open-gripper samples target the TCP; the scored target stays
    the TCP's."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from rvt2cli.data.paths import episode_paths
    from rvt2cli.model.config import SMALL
    from rvt2cli.train.batches import make_batch
    from rvt2cli.train.packed import pack
    from rvt2cli.train.samples import load_samples

    samples = load_samples(episode_paths([str(tiny_dataset)]), progress=False)
    lang = torch.zeros(len(samples.instructions), SMALL.lang_tokens, 384)
    everything = list(range(len(samples)))
    offset = np.array([0.1, 0.0, 0.02])
    plain = pack(samples, everything, lang, 2000, "cpu")
    aimed = pack(samples, everything, lang, 2000, "cpu", aim_offsets={"stack_cube": list(offset)})
    idx = np.arange(len(samples))
    held = ~aimed.gripper_open
    assert held.any() and (~held).any()
    for generator in (None, torch.Generator().manual_seed(0)):
        batch = make_batch(aimed, idx, SMALL, generator)
        metres = aimed.half[aimed.task][:, None]
        ahead = ((batch.position - batch.tcp_position).numpy() * metres)
        turned = Rotation.from_quat(batch.quaternion).apply(offset)
        assert np.allclose(ahead[held], turned[held], atol=1e-5) and np.allclose(ahead[~held], 0.0)
        assert np.allclose(batch.obs.aim[~held].numpy(), 0.0)
        assert np.allclose(batch.obs.aim[held].numpy() * metres[held], offset, atol=1e-6)
    assert torch.allclose(make_batch(aimed, idx, SMALL).tcp_position, make_batch(plain, idx, SMALL).position, atol=1e-6)


def test_aim_held_needs_a_task_that_declares_an_aim_offset(tiny_dataset, tmp_path, cli):
    r = cli("train", "--data", tiny_dataset, "--out", tmp_path / "aim", "--aim-held", "--config", "small", "--steps", "2",
            "--no-progress")
    assert_one_line_error(r, "--aim-held", "stack_cube", "aim_offset")
    assert not (tmp_path / "aim").exists() or not any((tmp_path / "aim").iterdir())


def test_task_set_trains_on_the_sets_episodes_only(tiny_dataset, tmp_path, cli):
    from rvt2cli.train.training_data import load_training_data

    samples, _ = load_training_data([str(tiny_dataset)], False, False, keyframe_starts_only=True, task_set="maniskill9")
    assert samples.tasks == ["stack_cube"] and len(samples) > 0
    with pytest.raises(UserError, match="no training samples .* of the tasks .*slide_block_to_color_target"):
        load_training_data([str(tiny_dataset)], False, False, keyframe_starts_only=True, task_set="rlbench18")
    r = cli("train", "--data", tiny_dataset, "--out", tmp_path / "set", "--task-set", "nope", "--config", "small",
            "--steps", "2", "--no-progress")
    assert_one_line_error(r, "unknown task set 'nope'")


def test_compiled_policy_under_ddp_is_traced_as_whole_graphs(tiny_dataset, tmp_path):
    """Under DistributedDataParallel, rvt2 compiles each stage as one graph: Dynamo's default cut at DDP's
    gradient buckets gave non-finite bf16 losses on 2 x H200 (rvt2cli.train.training_setup.data_parallel). The
    wrapped, compiled policy computes what the policy computes alone."""
    import torch._dynamo
    import torch.distributed as dist

    from rvt2cli.model.config import get_config
    from rvt2cli.model.policy import RVT2Policy
    from rvt2cli.train.batches import BatchStream
    from rvt2cli.train.data_sharing import load_data
    from rvt2cli.train.training_setup import data_parallel

    cfg = get_config("small")
    opts = TrainOptions(data=[str(tiny_dataset)], out=str(tmp_path / "x"), **TINY_TRAIN)
    packed = load_data(opts, cfg, torch.device("cpu"), False, None, lambda *_: None).packed
    batch = next(BatchStream(packed, cfg, torch.Generator().manual_seed(0), 2))
    torch.manual_seed(0)
    policy = RVT2Policy(cfg, render_backend="torch")
    with policy.eager():
        expected = policy(batch.obs, batch.position, batch.rot_bins, batch.stage2_center)
    default = torch._dynamo.config.optimize_ddp
    dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
    try:
        torch._dynamo.reset()
        policy.compile_network()
        model = data_parallel(policy, torch.device("cpu"))
        assert torch._dynamo.config.optimize_ddp is False
        got = model(batch.obs, batch.position, batch.rot_bins, batch.stage2_center)
        for name, value in expected.items():
            if isinstance(value, torch.Tensor) and value.is_floating_point():
                torch.testing.assert_close(got[name], value, rtol=1e-4, atol=1e-4, msg=name)
    finally:
        dist.destroy_process_group()
        torch._dynamo.config.optimize_ddp = default
        torch._dynamo.reset()


def test_phrasings_all_draws_each_phrasing_of_the_demos_variation(tiny_dataset, tmp_path):
    import numpy as np

    from rvt2cli.data.paths import episode_paths
    from rvt2cli.model.config import get_config
    from rvt2cli.tasks import get_task
    from rvt2cli.train.batches import make_batch
    from rvt2cli.train.packed import pack
    from rvt2cli.train.samples import load_samples, phrasing_table

    samples = load_samples(episode_paths([str(tiny_dataset)]), progress=False)
    texts, table, counts = phrasing_table(samples)
    own = samples.instructions[0]
    phrasings = get_task("stack_cube").phrasings(own)
    assert len(phrasings) == 3 and own in phrasings                  # the task's three templates, one variation
    assert texts[: len(samples.instructions)] == samples.instructions  # the demos' own keep their indices
    assert {texts[j] for j in table[0][: counts[0]]} == set(phrasings)
    # each row of this language table holds its own index, so a batch's rows say which phrasing was drawn
    lang = torch.arange(len(texts), dtype=torch.float32)[:, None, None].expand(len(texts), 2, 4).contiguous()
    indices = [i for i in range(len(samples)) if samples.instruction_index[i] == 0][:4]
    cfg = get_config("small")

    def drawn(packed, generator):
        batch = make_batch(packed, np.repeat(np.arange(len(indices)), 16), cfg, generator)
        return batch.obs.lang[:, 0, 0].long().tolist()

    with_phrasings = pack(samples, indices, lang, 3000, "cpu", phrasings=(table, counts))
    first = drawn(with_phrasings, torch.Generator().manual_seed(1))
    assert set(first) == set(table[0][: counts[0]].tolist())            # every phrasing of the variation, 64 draws
    assert drawn(with_phrasings, torch.Generator().manual_seed(1)) == first   # deterministic given the seed
    assert set(drawn(with_phrasings, None)) == {0}                      # validation batches: the demo's own
    assert set(drawn(pack(samples, indices, lang, 3000, "cpu"), torch.Generator().manual_seed(1))) == {0}  # --phrasings demo

    run = tmp_path / "all"
    train(TrainOptions(data=[str(tiny_dataset)], out=str(run), steps=2, save_every=2, phrasings="all", **TINY_TRAIN),
          say=lambda *_: None)
    ckpt = load_checkpoint(run)
    assert set(phrasings) <= set(ckpt.instruction_embeddings)          # every phrasing trained on is kept with it
    assert json.loads((run / "run.json").read_text())["options"]["phrasings"] == "all"


def test_phrasings_first_trains_every_sample_on_its_variations_first_phrasing(tiny_dataset, tmp_path):
    """--phrasings first, the paper's training: each demo's words become its variation's first trained phrasing
    (RLBench's descriptions[0]), whichever phrasing its seed drew; the checkpoint knows no other."""
    from rvt2cli.data.paths import episode_paths
    from rvt2cli.tasks import get_task
    from rvt2cli.train.samples import load_samples, trained_instructions

    samples = load_samples(episode_paths([str(tiny_dataset)]), progress=False)
    first = get_task("stack_cube").first_phrasing(0)
    assert trained_instructions(samples, "demo") == samples.instructions
    assert trained_instructions(samples, "first") == [first] * len(samples.instructions)
    run = tmp_path / "first"
    train(TrainOptions(data=[str(tiny_dataset)], out=str(run), steps=2, save_every=2, phrasings="first", **TINY_TRAIN),
          say=lambda *_: None)
    assert set(load_checkpoint(run).instruction_embeddings) == {first}
