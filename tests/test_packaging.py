"""The package as users get it: every subpackage ships, the CLI lists its commands, and the
benchmarks run (tiny configurations)."""

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).parent.parent


def test_every_subpackage_is_listed_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "rvt2cli").rglob("__init__.py")}
    assert found <= listed, found - listed


def test_cli_help_lists_the_commands_in_data_flow_order(cli):
    r = cli("--help")
    assert r.returncode == 0
    order = [r.stdout.index(f"    {c}") for c in ("record", "info", "extract-keyframes", "render", "train", "eval", "export")]
    assert order == sorted(order)
    assert cli("--version").stdout.startswith("rvt2 ")



def test_doctor_finds_every_library_rvt2_loads_at_run_time(cli):
    """`rvt2 doctor` names the simulator's, the data's and serving's libraries with their versions, and here
    (a complete install) none is MISSING: a machine missing one (an offline kit's site without websockets) says
    so in its first command, not when `rvt2 eval --shared-policy` imports it."""
    r = cli("doctor", "--no-render-check")
    assert r.returncode == 0
    found = dict(line.split(None, 1) for line in r.stdout.splitlines() if line.strip() and not line.startswith("ROS"))
    for library in ("sapien", "mani-skill", "mplib", "mcap", "warp", "websockets", "msgpack"):
        assert library in found and not found[library].startswith("MISSING"), (library, r.stdout)
    assert "MISSING" not in r.stdout


@pytest.mark.sim
@pytest.mark.slow
def test_benchmarks_run_in_a_tiny_configuration(tmp_path):
    r = subprocess.run([sys.executable, "-m", "benchmarks.run_all", "--quick", "--out", str(tmp_path)], cwd=ROOT,
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    for name in ("render", "policy", "gemm", "record"):
        assert json.loads((tmp_path / f"{name}.json").read_text())
    assert "## policy" in (tmp_path / "summary.md").read_text()
