"""Checkpoints: a folder per save, and a `last` pointer in the run folder.

    runs/NAME/last                          -> "checkpoints/step_000500"
    runs/NAME/checkpoints/step_000500/
        config.json                         model config, tasks, workspaces, instructions, versions
        model.safetensors                   weights
        instructions.safetensors            token embeddings of the training instructions
        training_state.pt                   optimiser, schedule, RNG states (for --resume)

Each save is written to a temporary folder and renamed; `last` is replaced atomically after it.
"""

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from rvt2cli import __version__
from rvt2cli.atomic import atomic_open
from rvt2cli.errors import UserError
from rvt2cli.model.config import ModelConfig

CHECKPOINT_FORMAT = 1
CONFIG = "config.json"
WEIGHTS = "model.safetensors"
INSTRUCTIONS = "instructions.safetensors"
STATE = "training_state.pt"


@dataclass
class Checkpoint:
    path: Path
    config: ModelConfig
    info: dict                       # tasks, bounds, instructions, step, versions
    weights: dict[str, torch.Tensor]
    instruction_embeddings: dict[str, torch.Tensor]

    def state(self) -> dict:
        return torch.load(self.path / STATE, map_location="cpu", weights_only=False)


def save_checkpoint(run_dir: Path, step: int, model: torch.nn.Module, cfg: ModelConfig, info: dict,
                    instructions: dict[str, torch.Tensor], training_state: dict) -> Path:
    final = run_dir / "checkpoints" / f"step_{step:07d}"
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        texts = sorted(instructions)
        config = {"rvt2_version": __version__, "checkpoint_format": CHECKPOINT_FORMAT, "step": step,
                  "model": cfg.to_dict(), "instructions": texts, **info}
        (tmp / CONFIG).write_text(json.dumps(config, indent=2))
        save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}, str(tmp / WEIGHTS))
        embeddings = torch.stack([instructions[t] for t in texts]) if texts else torch.zeros(0)
        save_file({"embeddings": embeddings.contiguous()}, str(tmp / INSTRUCTIONS))
        torch.save(training_state, tmp / STATE)
        shutil.rmtree(final, ignore_errors=True)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    with atomic_open(run_dir / "last", "w") as f:
        f.write(f"checkpoints/{final.name}\n")
    return final


def resolve(path: str | Path) -> Path:
    """A run folder (follows `last`) or a checkpoint folder -> the checkpoint folder."""
    path = Path(path)
    if (path / "last").is_file():
        path = path / (path / "last").read_text().strip()
    if not path.exists():
        raise UserError(f"{path}: no such checkpoint (give a run folder written by `rvt2 train`, or one of its checkpoints)")
    if not (path / CONFIG).is_file() or not (path / WEIGHTS).is_file():
        raise UserError(f"{path}: not an rvt2 checkpoint (no {CONFIG} and {WEIGHTS}); give a run folder written by `rvt2 train`")
    return path


def load_checkpoint(path: str | Path) -> Checkpoint:
    path = resolve(path)
    try:
        config = json.loads((path / CONFIG).read_text())
    except json.JSONDecodeError:
        raise UserError(f"{path / CONFIG}: damaged checkpoint config (not JSON)") from None
    version = config.get("checkpoint_format")
    if not isinstance(version, int) or "model" not in config:
        raise UserError(f"{path}: not an rvt2 checkpoint (its {CONFIG} has no checkpoint_format/model)")
    if version > CHECKPOINT_FORMAT:
        raise UserError(f"{path}: checkpoint format {version} is newer than this rvt2 reads ({CHECKPOINT_FORMAT}); upgrade rvt2")
    try:
        cfg = ModelConfig.from_dict(config["model"])
    except (TypeError, ValueError) as e:
        raise UserError(f"{path}: checkpoint of another model version ({e})") from None
    weights = load_file(str(path / WEIGHTS))
    embeddings = load_file(str(path / INSTRUCTIONS))["embeddings"] if (path / INSTRUCTIONS).exists() else None
    texts = config.get("instructions", [])
    instructions = {t: embeddings[i] for i, t in enumerate(texts)} if embeddings is not None and len(texts) else {}
    info = {k: v for k, v in config.items() if k not in ("model",)}
    return Checkpoint(path=path, config=cfg, info=info, weights=weights, instruction_embeddings=instructions)


def load_policy(path: str | Path, device="cpu", render_backend: str = "warp"):
    """A checkpoint's policy in eval mode, ready for `predict`, and the checkpoint itself."""
    from rvt2cli.model.policy import RVT2Policy

    ckpt = load_checkpoint(path)
    policy = RVT2Policy(ckpt.config, render_backend=render_backend)
    missing, unexpected = policy.load_state_dict(ckpt.weights, strict=False)
    if missing or unexpected:
        raise UserError(f"{ckpt.path}: checkpoint of another model version ({len(missing)} missing, "
                        f"{len(unexpected)} unexpected weights, e.g. {(missing or unexpected)[0]})")
    return policy.to(device).eval(), ckpt
