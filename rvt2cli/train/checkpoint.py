"""Checkpoints: a folder per save, and a `last` pointer in the run folder.

    runs/NAME/last                          -> "checkpoints/step_000500"
    runs/NAME/checkpoints/step_000500/
        config.json                         model config, tasks, workspaces, instructions, run options, versions
        model.safetensors                   weights
        instructions.safetensors            token embeddings of the training instructions
        training_state.pt                   optimiser, schedule, every rank's RNG states (for --resume);
                                            plain tensors and numbers, loaded with torch.load(weights_only=True)

Each save is written to a temporary folder and renamed; `last` is replaced atomically after it.
"""

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from rvt2cli import __version__
from rvt2cli.atomic import atomic_folder, atomic_open
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
    info: dict                       # tasks, bounds, rigs, instructions, step, options, versions
    weights: dict[str, torch.Tensor]
    instruction_embeddings: dict[str, torch.Tensor]

    @property
    def tasks(self) -> list[str]:
        return list(self.info.get("tasks", []))

    @property
    def training_options(self) -> dict:
        """The run's options as `rvt2 train` kept them (TrainOptions.to_json); {} for a checkpoint without them."""
        return self.info.get("options") or {}

    @property
    def aim_offsets(self) -> dict[str, list[float]] | None:
        """Task -> aim offset (m, TCP frame) of a policy trained with `--aim-held`; None: it aims the TCP."""
        return self.info.get("aim_offsets")

    def aim_offset(self, task: str) -> list[float] | None:
        """This task's aim offset, where the policy was trained with one."""
        return (self.aim_offsets or {}).get(task)

    def scene_bounds(self, task: str) -> list[float]:
        """The bounds the policy saw this task with; for a task it was not trained on, the task's own."""
        if task in self.info.get("bounds", {}):
            return list(self.info["bounds"][task])
        from rvt2cli.tasks import DEFAULT_SCENE_BOUNDS, all_tasks

        known = all_tasks().get(task)
        return list(known.scene_bounds if known else DEFAULT_SCENE_BOUNDS)

    def state(self) -> dict:
        """The training state for --resume (tensors and numbers only: no code runs while loading)."""
        path = self.path / STATE
        try:
            return torch.load(path, map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise UserError(f"{path}: missing; this checkpoint cannot be resumed (it holds weights only)") from None
        except Exception as e:  # noqa: BLE001 - pickle and torch raise many types for a bad or unsafe file
            first = str(e).strip().splitlines()[0][:160] if str(e).strip() else type(e).__name__
            raise UserError(f"{path}: not a training state rvt2 can load safely ({first}); "
                            "resume from a checkpoint written by `rvt2 train`") from None


def checkpoint_folder(run_dir: Path, step: int) -> Path:
    """Where `rvt2 train` keeps a run's checkpoint of this step."""
    return Path(run_dir) / "checkpoints" / f"step_{step:07d}"


def save_checkpoint(run_dir: Path, step: int, model: torch.nn.Module, cfg: ModelConfig, info: dict,
                    instructions: dict[str, torch.Tensor], training_state: dict) -> Path:
    final = checkpoint_folder(run_dir, step)
    with atomic_folder(final, replace=True) as tmp:  # a save of the same step (a resumed run) replaces it
        texts = sorted(instructions)
        config = {"rvt2_version": __version__, "checkpoint_format": CHECKPOINT_FORMAT, "step": step,
                  "model": cfg.to_dict(), "instructions": texts, **info}
        (tmp / CONFIG).write_text(json.dumps(config, indent=2))
        save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}, str(tmp / WEIGHTS))
        embeddings = torch.stack([instructions[t] for t in texts]) if texts else torch.zeros(0)
        save_file({"embeddings": embeddings.contiguous()}, str(tmp / INSTRUCTIONS))
        torch.save(training_state, tmp / STATE)
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


def _load_tensors(path: Path) -> dict[str, torch.Tensor]:
    try:
        return load_file(str(path))
    except (SafetensorError, OSError, ValueError) as e:
        raise UserError(f"{path}: damaged or not a safetensors file ({str(e)[:120]}); "
                        "use another checkpoint or train again") from None


def load_checkpoint(path: str | Path) -> Checkpoint:
    path = resolve(path)
    try:
        config = json.loads((path / CONFIG).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise UserError(f"{path / CONFIG}: damaged checkpoint config (not JSON)") from None
    version = config.get("checkpoint_format") if isinstance(config, dict) else None
    if not isinstance(version, int) or "model" not in config:
        raise UserError(f"{path}: not an rvt2 checkpoint (its {CONFIG} has no checkpoint_format/model)")
    if version > CHECKPOINT_FORMAT:
        raise UserError(f"{path}: checkpoint format {version} is newer than this rvt2 reads ({CHECKPOINT_FORMAT}); upgrade rvt2")
    try:
        cfg = ModelConfig.from_dict(config["model"])
        cfg.validate()
    except (TypeError, ValueError, KeyError) as e:
        raise UserError(f"{path}: checkpoint of another model version ({e})") from None
    weights = _load_tensors(path / WEIGHTS)
    embeddings = _load_tensors(path / INSTRUCTIONS).get("embeddings") if (path / INSTRUCTIONS).exists() else None
    texts = config.get("instructions", [])
    instructions = {t: embeddings[i] for i, t in enumerate(texts)} if embeddings is not None and len(texts) else {}
    info = {k: v for k, v in config.items() if k not in ("model",)}
    return Checkpoint(path=path, config=cfg, info=info, weights=weights, instruction_embeddings=instructions)


def load_weights(model: torch.nn.Module, ckpt: Checkpoint) -> None:
    """Put a checkpoint's weights into a model built from its config; one line if they do not fit."""
    expected = model.state_dict()
    missing = [k for k in expected if k not in ckpt.weights]
    unexpected = [k for k in ckpt.weights if k not in expected]
    wrong = [k for k in expected if k in ckpt.weights and ckpt.weights[k].shape != expected[k].shape]
    if missing or unexpected or wrong:
        example = (f"{wrong[0]} is {tuple(ckpt.weights[wrong[0]].shape)}, the config needs {tuple(expected[wrong[0]].shape)}"
                   if wrong else (missing or unexpected)[0])
        raise UserError(f"{ckpt.path / WEIGHTS}: does not match {ckpt.path / CONFIG} ({len(missing)} missing, "
                        f"{len(unexpected)} unexpected, {len(wrong)} wrongly shaped weights, e.g. {example}); "
                        "the files come from different runs or model versions")
    model.load_state_dict(ckpt.weights)


def load_policy(path: str | Path, device="cpu", render_backend: str = "warp", stage2_min_points: int | None = None):
    """A checkpoint's policy in eval mode, ready for `predict`, and the checkpoint itself. `stage2_min_points`
    overrides the checkpoint's (an inference setting: `ModelConfig.stage2_min_points`)."""
    from dataclasses import replace

    from rvt2cli.model.policy import RVT2Policy

    ckpt = load_checkpoint(path)
    if stage2_min_points is not None:
        ckpt.config = replace(ckpt.config, stage2_min_points=stage2_min_points)
    policy = RVT2Policy(ckpt.config, render_backend=render_backend)
    load_weights(policy, ckpt)
    return policy.to(device).eval(), ckpt
