"""`rvt2 export`: ONNX and TorchScript policies that match the PyTorch policy on recorded observations."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_one_line_error
from rvt2cli.export.exporter import export_policy

pytestmark = pytest.mark.sim
EXAMPLE = Path(__file__).parent.parent / "examples" / "run_exported_policy.py"


@pytest.mark.parametrize("fmt", ["onnx", "torchscript"])
def test_export_matches_pytorch_on_recorded_observations(tiny_checkpoint, tiny_dataset, tmp_path, fmt, request):
    run_dir, _ = tiny_checkpoint
    out = tmp_path / "policy"
    if fmt == "onnx":  # through the CLI (the aimed checkpoint, exported once for the session by conftest)
        r, out = request.getfixturevalue("onnx_export")
        assert r.returncode == 0, r.stderr[-3000:]
        assert "parity on 4 observations" in r.stdout
        report = json.loads((out / "manifest.json").read_text())["parity"]
        assert report["max_position_error_m"] <= 0.001 and report["rotation_bins_equal"] and report["gripper_equal"]
    else:
        report = export_policy(str(run_dir), fmt, str(out), max_points=20000, check_data=(str(tiny_dataset),))
        assert report.samples == 4  # recorded observations, not a synthetic cloud
        assert report.max_position_error_m <= 0.001 and report.rotation_bins_equal and report.gripper_equal
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["format"] == fmt and (out / manifest["file"]).stat().st_size > 1_000_000
    assert manifest["tasks"]["stack_cube"]["scene_bounds"] and manifest["config"]["name"] == "small"
    assert json.loads((out / "instructions.json").read_text())
    # the runtime example uses only numpy, safetensors and onnxruntime / torch: not rvt2cli
    code = f"import sys, runpy; sys.modules['rvt2cli'] = None; sys.argv = ['x', {str(out)!r}]; runpy.run_path({str(EXAMPLE)!r})"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    assert len(result["position"]) == 3 and len(result["quaternion_xyzw"]) == 4


def test_export_refuses_missing_checkpoint(tmp_path, cli):
    assert_one_line_error(cli("export", "--checkpoint", tmp_path / "missing", "--out", tmp_path / "p"), "missing", "no such checkpoint")
    assert not (tmp_path / "p").exists()


def test_a_checkpoint_crosses_in_pieces_rounded_to_float16_or_exact(tiny_checkpoint, tmp_path):
    """scripts/offline-gpu-host/gpu_checkpoint.py: a run leaves a GPU machine without network access in
    pieces and is put back together elsewhere; --exact keeps the weights bit for bit (an evaluation
    resumed there runs the model its first episodes ran), the default rounds them to float16."""
    import torch
    from safetensors.torch import load_file

    from rvt2cli.train.checkpoint import WEIGHTS, resolve

    run_dir, _ = tiny_checkpoint
    script = Path(__file__).parent.parent / "scripts" / "offline-gpu-host" / "gpu_checkpoint.py"
    trained = load_file(str(resolve(run_dir) / WEIGHTS))
    for exact in (True, False):
        pieces, restored = tmp_path / f"pieces_{exact}", tmp_path / f"run_{exact}"
        for command in (["shrink", str(run_dir), str(pieces)] + (["--exact"] if exact else []),
                        ["restore", str(pieces), str(restored)]):
            r = subprocess.run([sys.executable, str(script), *command], capture_output=True, text=True, timeout=300)
            assert r.returncode == 0, r.stderr[-2000:]
        weights = load_file(str(resolve(restored) / WEIGHTS))
        assert weights.keys() == trained.keys()
        for name, value in trained.items():
            expected = value if exact or not value.is_floating_point() else value.half().float()
            assert torch.equal(weights[name], expected), name
        assert ("transfer" in json.loads((pieces / "config.json").read_text())) != exact


def test_a_stopped_training_crosses_in_pieces_and_goes_on_there_as_if_never_stopped(tiny_dataset, tmp_path):
    """gpu_checkpoint.py --resumable: a run stopped by --time-limit leaves one machine in pieces (its training
    state and logs with it), is put back together in another folder, and `--resume` there ends at the weights
    and losses of the run that never stopped. A checkpoint restored for evaluation has no training state: one
    line, no pieces."""
    import torch

    from conftest import TINY_TRAIN
    from rvt2cli.train.checkpoint import load_checkpoint
    from rvt2cli.train.trainer import TrainOptions, train

    script = Path(__file__).parent.parent / "scripts" / "offline-gpu-host" / "gpu_checkpoint.py"
    sys.path.insert(0, str(script.parent))
    from gpu_checkpoint import all_pieces
    opts = dict(data=[str(tiny_dataset)], steps=6, save_every=6, log_every=3, **TINY_TRAIN)
    straight = train(TrainOptions(out=str(tmp_path / "a"), **opts), say=lambda *_: None)
    stopped = train(TrainOptions(out=str(tmp_path / "b"), time_limit=1e-9, **opts), say=lambda *_: None)
    pieces, elsewhere = tmp_path / "pieces", tmp_path / "elsewhere"
    # on the way out again the pieces are cut to the room a transfer leaves (resplit): the same bytes arrive
    for command in (["shrink", str(tmp_path / "b"), str(pieces), "--resumable"], ["resplit", str(pieces), "--piece-mib", "0.25"],
                    ["restore", str(pieces), str(elsewhere)]):
        r = subprocess.run([sys.executable, str(script), *command], capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
        if command[0] == "shrink":
            sent = json.loads((pieces / "manifest.json").read_text())
        if command[0] == "resplit":
            cut = json.loads((pieces / "manifest.json").read_text())
            assert len(cut["pieces"]) > len(sent["pieces"]) and cut["sha256"] == sent["sha256"]
            assert cut["state"]["sha256"] == sent["state"]["sha256"] and (pieces / "config.json").is_file()
            assert max(f.stat().st_size for f in pieces.glob("*.part*")) <= 2**18
            assert sorted(f.name for f in pieces.glob("*.part*")) == sorted(all_pieces(cut))
    assert "--resume" in r.stdout
    resumed = train(TrainOptions(out=str(elsewhere), resume=True, **opts), say=lambda *_: None)
    assert stopped.steps == 3 and stopped.losses + resumed.losses == straight.losses
    a, c = load_checkpoint(tmp_path / "a").weights, load_checkpoint(elsewhere).weights
    assert all(torch.equal(a[k], c[k]) for k in a)
    assert [line.split(",")[0] for line in (elsewhere / "train.csv").read_text().splitlines()] == ["step", "3", "6"]

    with open(pieces / cut["state"]["pieces"][0], "r+b") as f:  # a damaged piece: one line, nothing cut
        f.write(b"\0")
    r = subprocess.run([sys.executable, str(script), "resplit", str(pieces), "--piece-mib", "1"], capture_output=True, text=True)
    assert r.returncode == 1 and "sha256 differs" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert json.loads((pieces / "manifest.json").read_text()) == cut

    exact = tmp_path / "exact"
    for command in (["shrink", str(tmp_path / "b"), str(exact), "--exact"], ["restore", str(exact), str(tmp_path / "for_eval")],
                    ["shrink", str(tmp_path / "for_eval"), str(tmp_path / "again"), "--resumable"]):
        r = subprocess.run([sys.executable, str(script), *command], capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and "cannot be trained on" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "again").exists()


def test_an_export_keeps_stage_1s_point_where_the_checkpoint_says_stage_2_saw_too_little(tiny_checkpoint, tmp_path):
    """A checkpoint's `stage2_min_points` travels into its export: with a minimum no box reaches, the exported
    policy answers stage 1's point, as the PyTorch policy does, and not stage 2's."""
    from rvt2cli.export.deployable import example_inputs
    from rvt2cli.export.exporter import load_exported
    from rvt2cli.model.observation import Observation, aim_vector
    from rvt2cli.render.workspace import center_and_half
    from rvt2cli.train.checkpoint import load_policy, resolve

    blind = tmp_path / "checkpoint"
    shutil.copytree(resolve(tiny_checkpoint[0]), blind)
    config = json.loads((blind / "config.json").read_text())
    config["model"]["stage2_min_points"] = 10**9
    (blind / "config.json").write_text(json.dumps(config))
    report = export_policy(str(blind), "torchscript", str(tmp_path / "policy"), max_points=20000)
    assert report.max_position_error_m <= 0.001 and report.rotation_bins_equal
    manifest = json.loads((tmp_path / "policy" / "manifest.json").read_text())
    assert manifest["config"]["stage2_min_points"] == 10**9

    policy, _ = load_policy(blind, render_backend="torch", stage2_min_points=0)  # both stages' points, to compare
    xyz, rgb, num_points, proprio, lang, bounds, aim = inputs = example_inputs(policy.cfg, 20000)
    center, half = center_and_half(bounds)
    pred = policy.predict(Observation(points=(xyz - center) / half, rgb=rgb, num_points=num_points, proprio=proprio,
                                      lang=lang, aim=aim_vector(aim, proprio[:, 0] > 0.5, half)))
    stage1, stage2 = ((p * half + center).numpy()[0] for p in (pred.stage1_position, pred.position))
    exported = load_exported(tmp_path / "policy", manifest)(*inputs)[0][0]
    assert np.abs(exported - stage1).max() <= 0.001 < np.abs(exported - stage2).max()

    # `rvt2 export --stage2-min-points 0` overrides the checkpoint's: stage 2's point again
    export_policy(str(blind), "torchscript", str(tmp_path / "policy0"), max_points=20000, stage2_min_points=0)
    manifest = json.loads((tmp_path / "policy0" / "manifest.json").read_text())
    assert manifest["config"]["stage2_min_points"] == 0
    assert np.abs(load_exported(tmp_path / "policy0", manifest)(*inputs)[0][0] - stage2).max() <= 0.001
    # deployment: a checkpoint takes the override, an export keeps what it was exported with
    from rvt2cli.deploy import KeyframePolicy
    from rvt2cli.errors import UserError

    assert KeyframePolicy.load(blind, stage2_min_points=0).describe()["config"]["stage2_min_points"] == 0
    with pytest.raises(UserError, match="export again with `rvt2 export --stage2-min-points N`"):
        KeyframePolicy.load(tmp_path / "policy", stage2_min_points=0)
