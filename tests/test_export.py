"""`rvt2 export`: ONNX and TorchScript policies that match the PyTorch policy on recorded observations."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import assert_one_line_error
from rvt2cli.export.exporter import export_policy

pytestmark = pytest.mark.sim
EXAMPLE = Path(__file__).parent.parent / "examples" / "run_exported_policy.py"


@pytest.mark.parametrize("fmt", ["onnx", "torchscript"])
def test_export_matches_pytorch_on_recorded_observations(tiny_checkpoint, tiny_dataset, tmp_path, fmt, cli):
    run_dir, _ = tiny_checkpoint
    out = tmp_path / "policy"
    if fmt == "onnx":  # through the CLI: a fresh process, where the export is the first thing traced
        r = cli("export", "--checkpoint", run_dir, "--format", fmt, "--out", out, "--max-points", "20000",
                "--check-data", tiny_dataset)
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
