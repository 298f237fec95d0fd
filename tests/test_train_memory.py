"""Training within less GPU memory: the clouds on the host (`--samples-on host`) and a batch run in parts
(`--micro-batch`), each the same training as before, on the tiny dataset's real samples and the small
config on the CPU."""

import copy
from dataclasses import fields, replace

import pytest
import torch

from conftest import TINY_TRAIN
from rvt2cli.errors import UserError
from rvt2cli.model.config import get_config
from rvt2cli.model.policy import RVT2Policy
from rvt2cli.train.batches import Batch, BatchStream, MicroBatches
from rvt2cli.train.optim import make_optimizer, warmup_cosine
from rvt2cli.train.step import TrainStep
from rvt2cli.train.trainer import TrainOptions, train
from rvt2cli.train.training_data import read_data

pytestmark = pytest.mark.sim

CPU = torch.device("cpu")
SMALL = get_config("small")


def quiet(*_):
    pass


@pytest.fixture(scope="module")
def options(tiny_dataset, tmp_path_factory):
    # every drawn random number in play: augmentation, a phrasing per draw, the stage-2 centre's noise
    return TrainOptions(data=[str(tiny_dataset)], out=str(tmp_path_factory.mktemp("memory") / "run"),
                        **{**TINY_TRAIN, "augment": True, "max_points": 3000}, phrasings="all")


def batch_tensors(batch: Batch) -> dict[str, torch.Tensor]:
    """Every tensor a batch gives the step, by name."""
    out = {f"obs.{f.name}": getattr(batch.obs, f.name) for f in fields(batch.obs) if torch.is_tensor(getattr(batch.obs, f.name))}
    out.update({f.name: getattr(batch, f.name) for f in fields(batch) if torch.is_tensor(getattr(batch, f.name))})
    return out


def test_clouds_on_the_host_give_the_batches_of_clouds_on_the_device_bit_for_bit(options):
    """The host's path (rows gathered with index_select, then moved: pinned and on a side stream on a GPU)
    makes, draw for draw, the batches that indexing the packed clouds where they live made, which is how
    every run drew its batches before; the generators end in the same state."""
    on_device = read_data(replace(options, samples_on="device"), SMALL, CPU, False, None, quiet).packed
    on_host = read_data(replace(options, samples_on="host"), SMALL, CPU, False, None, quiet).packed
    assert on_host.clouds_on_host and not on_device.clouds_on_host
    assert torch.equal(on_host.xyz, on_device.xyz) and torch.equal(on_host.rgb, on_device.rgb)
    host_stream = BatchStream(on_host, SMALL, torch.Generator().manual_seed(5), 6)
    device_stream = BatchStream(on_device, SMALL, torch.Generator().manual_seed(5), 6)
    assert host_stream.rows is not None and device_stream.rows is None
    for _ in range(3):
        a, b = batch_tensors(next(host_stream)), batch_tensors(next(device_stream))
        assert a.keys() == b.keys() and "stage2_center" in a and "obs.lang" in a
        for name in a:
            assert torch.equal(a[name], b[name]), name
    assert torch.equal(host_stream.generator.get_state(), device_stream.generator.get_state())


def test_a_batch_in_micro_batches_takes_the_whole_batchs_step(options):
    """--micro-batch 2 of --batch-size 4: the same samples and random numbers as the whole batch (its parts
    are its rows), and after one LAMB step the same parameters within 1e-6 (float32 sums in another order),
    the same loss terms within 1e-5 relative."""
    packed = read_data(replace(options, samples_on="host"), SMALL, CPU, False, None, quiet).packed
    whole_stream = BatchStream(packed, SMALL, torch.Generator().manual_seed(7), 4)
    parts_stream = BatchStream(packed, SMALL, torch.Generator().manual_seed(7), 4, micro_batch=2)
    whole, parts = next(whole_stream), next(parts_stream)
    assert isinstance(parts, MicroBatches) and len(parts) == 2 and parts.weight(0) == 0.5
    assert torch.equal(whole_stream.generator.get_state(), parts_stream.generator.get_state())
    whole_rows = batch_tensors(whole)
    for i, part in enumerate(parts):
        for name, value in batch_tensors(part).items():
            assert torch.allclose(value, whole_rows[name][2 * i:2 * i + 2], rtol=0, atol=1e-6), name

    torch.manual_seed(0)
    policy = RVT2Policy(SMALL, render_backend="torch")
    initial, policies = copy.deepcopy(policy), (policy, copy.deepcopy(policy))
    results = []
    for p, batch in zip(policies, (whole, parts)):
        optimizer, _ = make_optimizer(p.parameters(), 3e-3, 1e-4, CPU)
        results.append(TrainStep(p, optimizer, warmup_cosine(optimizer, 1, 10), amp=False, clip=5.0)(batch))
    for name, value in results[0].losses.items():
        assert torch.allclose(value, results[1].losses[name], rtol=1e-5), name
    assert bool(results[0].finite) and bool(results[1].finite)
    changed = False
    for a, b, before in zip(policies[0].parameters(), policies[1].parameters(), initial.parameters()):
        assert torch.allclose(a, b, rtol=0, atol=1e-6)
        changed |= not torch.equal(a, before)
    assert changed


def test_a_micro_batch_must_divide_the_batch(options, tmp_path):
    with pytest.raises(UserError, match="--micro-batch 3 does not divide --batch-size 8"):
        train(replace(options, out=str(tmp_path / "run"), micro_batch=3), say=quiet)
    assert not (tmp_path / "run").exists()


_SHARDED_CHECK = """
import sys
from dataclasses import replace

import torch

from rvt2cli.train.checkpoint import load_checkpoint
from rvt2cli.train.trainer import TrainOptions, train
from rvt2cli.train.training_state import init_distributed

rank, world = init_distributed()
base = TrainOptions(data=[sys.argv[1]], out="", config="small", batch_size=4, steps=3, save_every=3, max_points=3000,
                    val_episodes=0, augment=True, phrasings="all", progress=False)
runs = {}
for name, on, micro in (("device", "device", None), ("host", "host", None), ("host_micro", "host", 2)):
    runs[name] = train(replace(base, out=f"{sys.argv[2]}/{name}", samples_on=on, micro_batch=micro), say=lambda *_: None)
host, device = runs["host"].packed, runs["device"].packed
assert host.shard == (rank, world) and device.shard is None and not device.clouds_on_host
assert len(host.xyz) == len(range(rank, len(host), world)) < len(device.xyz)
assert torch.equal(host.xyz, device.xyz[rank::world])
assert runs["host"].losses == runs["device"].losses, (runs["host"].losses, runs["device"].losses)
assert torch.allclose(torch.tensor(runs["host_micro"].losses), torch.tensor(runs["device"].losses), rtol=1e-5)
if rank == 0:
    weights = {name: load_checkpoint(f"{sys.argv[2]}/{name}").weights for name in runs}
    for key, value in weights["device"].items():
        assert torch.equal(weights["host"][key], value), key
        assert torch.allclose(weights["host_micro"][key], value, rtol=0, atol=1e-5), key
print(f"rank {rank} of {world}: the same batches from its shard", flush=True)
"""


def test_processes_train_on_shards_of_the_host_clouds_as_on_whole_copies(options, tmp_path):
    """Two processes (gloo): with the clouds on the host each holds every other sample's clouds and gets the
    rest of its batches' rows from the other; the losses and weights are bit for bit those of two
    processes with a whole copy each, and in micro-batches (DDP averaging the gradients in the last part's
    backward pass only) within float tolerance."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = tmp_path / "check.py"
    script.write_text(_SHARDED_CHECK)
    torchrun = Path(sys.executable).parent / "torchrun"
    r = subprocess.run([str(torchrun), "--nproc-per-node", "2", str(script), options.data[0], str(tmp_path / "runs")],
                       capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr[-3000:]
    assert "rank 0 of 2: the same" in r.stdout and "rank 1 of 2: the same" in r.stdout


def test_memory_bench_trains_with_the_clouds_on_each_side(options, tmp_path):
    """benchmarks/memory_bench.py --quick: `rvt2 train` three ways on one read of the samples (clouds on the
    device, on the host, on the host in micro-batches), each with its rate and where its clouds are."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    out = tmp_path / "memory.json"
    r = subprocess.run([sys.executable, "-m", "benchmarks.memory_bench", "--data", options.data[0], "--quick",
                        "--json", str(out)], cwd=Path(__file__).parent.parent, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = json.loads(out.read_text())["variants"]
    assert list(rows) == ["device", "host", "host+micro"]
    assert [rows[name]["clouds_on"] for name in rows] == ["cpu", "host", "host"]
    assert rows["host+micro"]["micro_batch"] == 2 and all(row["samples_per_s"] > 0 for row in rows.values())
    assert "| host+micro (2) |" in r.stdout
