"""Training samples packed into one safetensors file, to train on a machine without the simulator stack.

`rvt2 pack-samples demos/ --out samples.safetensors` fuses every sample's cloud once and stores it with
the targets and the instruction embeddings; `rvt2 train --data samples.safetensors` then needs neither the
MCAP libraries nor the text encoder. Clouds are stored quantised to 16 bits per axis inside the task's
scene bounds (every fused point lies inside them), a step of at most 1/65535 of the workspace
(~0.02 mm for a 1.2 m workspace), and planar ([3, points]) so that general-purpose compressors
(`xz --delta`) shrink the file further for transfer.

    metadata  "rvt2_sample_cache": format version; "info": JSON (tasks, instructions, bounds, rigs, episodes)
    xyz       [3, P] uint16   quantised positions of all samples' points, concatenated
    rgb       [3, P] uint8
    offsets   [S + 1] int64   sample s owns points offsets[s]:offsets[s + 1]
    proprio, target_position, target_quaternion, target_gripper_open, target_ignore_collisions,
    task_index, instruction_index, episode_index, keyframe_start, keyframe_index, final_keyframe   [S, ...] per sample
    lang      [U, L, 384] float32   token embeddings of info["instructions"], in that order
"""

import json
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.numpy import load_file, save_file

from rvt2cli import __version__
from rvt2cli.atomic import atomic_path, ensure_folder
from rvt2cli.errors import UserError
from rvt2cli.runtime import usable_cores
from rvt2cli.train.samples import SampleSet, load_samples, select_samples

CACHE_FORMAT = 2  # 2: keyframe_index, final_keyframe per sample (format 1 files read with -1, "unknown", and False)
KEY = "rvt2_sample_cache"
LEVELS = 65535


def is_sample_cache(path: str | Path) -> bool:
    """A file whose safetensors header says it is an rvt2 sample cache."""
    path = Path(path)
    if not path.is_file() or path.suffix != ".safetensors":
        return False
    try:
        with safe_open(str(path), "np") as f:
            return KEY in (f.metadata() or {})
    except (SafetensorError, OSError, ValueError):
        return False


def _require_cache_name(path: Path) -> None:
    if path.suffix != ".safetensors":
        raise UserError(f"{path}: a sample cache is a .safetensors file; name it e.g. samples.safetensors")


def _quantise(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    unit = (xyz.astype(np.float64) - lo) / (hi - lo)
    return np.clip(np.rint(unit * LEVELS), 0, LEVELS).astype(np.uint16)


def _dequantise(q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return (q.astype(np.float64) / LEVELS * (hi - lo) + lo).astype(np.float32)


def save_sample_cache(samples: SampleSet, embeddings: dict[str, torch.Tensor], path: str | Path) -> Path:
    """Write `samples` and the embeddings of their instructions to `path` (atomically)."""
    path = Path(path)
    _require_cache_name(path)
    bounds = {t: np.asarray(samples.bounds[t], np.float64) for t in samples.tasks}
    xyz, offsets = [], [0]
    for i, points in enumerate(samples.xyz):
        b = bounds[samples.tasks[samples.task_index[i]]]
        xyz.append(_quantise(points, b[:3], b[3:]))
        offsets.append(offsets[-1] + len(points))
    tensors = {
        "xyz": np.ascontiguousarray(np.concatenate(xyz).T),
        "rgb": np.ascontiguousarray(np.concatenate(samples.rgb).T),
        "offsets": np.asarray(offsets, np.int64),
        "proprio": np.stack(samples.proprio).astype(np.float32),
        "target_position": np.stack(samples.target_position).astype(np.float32),
        "target_quaternion": np.stack(samples.target_quaternion).astype(np.float64),
        "target_gripper_open": np.asarray(samples.target_gripper_open, np.uint8),
        "target_ignore_collisions": np.asarray(samples.target_ignore_collisions, np.uint8),
        "task_index": np.asarray(samples.task_index, np.int64),
        "instruction_index": np.asarray(samples.instruction_index, np.int64),
        "episode_index": np.asarray(samples.episode_index, np.int64),
        "keyframe_start": np.asarray(samples.keyframe_start, np.uint8),
        "keyframe_index": np.asarray(samples.keyframe_index, np.int64),
        "final_keyframe": np.asarray(samples.final_keyframe, np.uint8),
        "lang": torch.stack([embeddings[t] for t in samples.instructions]).float().numpy(),
    }
    info = {"tasks": samples.tasks, "instructions": samples.instructions, "bounds": samples.bounds, "rigs": samples.rigs,
            "episodes": samples.episodes, "rvt2_version": __version__}
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata={KEY: str(CACHE_FORMAT), "info": json.dumps(info)})
    return path


def pack_sample_cache(data: list[str], out: str | Path, episodes_per_task: int | None = None,
                      keyframe_starts_only: bool = False, include_failures: bool = False, progress: bool = True,
                      cameras: tuple[str, ...] | None = None) -> str:
    """Load the episodes' samples, keep the selected ones, embed their instructions and save them to `out`."""
    from rvt2cli.data.paths import episode_paths
    from rvt2cli.model.config import CONFIGS
    from rvt2cli.model.language import InstructionCache

    out = Path(out)
    _require_cache_name(out)  # before minutes of loading
    ensure_folder(out.parent)
    samples = load_samples(episode_paths(data), include_failures, progress=progress, keyframe_starts_only=keyframe_starts_only,
                           cameras=cameras, workers=usable_cores())
    samples = samples.subset(select_samples(samples, episodes_per_task))
    cache = InstructionCache(max(c.lang_tokens for c in CONFIGS.values()))  # every config takes a prefix
    cache(samples.instructions)
    save_sample_cache(samples, cache.as_dict(), out)
    episodes = len(set(samples.episode_index))
    points = sum(len(x) for x in samples.xyz)
    return (f"{out}: {len(samples)} samples from {episodes} episodes of {len(samples.tasks)} task(s), "
            f"{points / max(len(samples), 1):.0f} points per cloud, {out.stat().st_size / 1e6:.1f} MB")


def load_sample_cache(path: str | Path) -> tuple[SampleSet, dict[str, torch.Tensor]]:
    """The samples and instruction embeddings stored by `save_sample_cache`."""
    path = Path(path)
    try:
        with safe_open(str(path), "np") as f:
            meta = f.metadata() or {}
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as e:
        raise UserError(f"{path}: not a readable sample cache ({e}); write it again with `rvt2 pack-samples`") from None
    if KEY not in meta:
        raise UserError(f"{path}: a safetensors file but not an rvt2 sample cache; write one with `rvt2 pack-samples`")
    if int(meta[KEY]) > CACHE_FORMAT:
        raise UserError(f"{path}: sample cache format {meta[KEY]} is newer than this rvt2 reads ({CACHE_FORMAT}); upgrade rvt2")
    info = json.loads(meta["info"])
    samples = SampleSet(tasks=info["tasks"], instructions=info["instructions"], bounds=info["bounds"], rigs=info["rigs"],
                        episodes=info["episodes"])
    offsets = tensors["offsets"]
    keyframe_index = tensors.get("keyframe_index", np.full(len(offsets) - 1, -1, np.int64))
    final_keyframe = tensors.get("final_keyframe", np.zeros(len(offsets) - 1, np.uint8))
    for i in range(len(offsets) - 1):
        task = samples.tasks[int(tensors["task_index"][i])]
        b = np.asarray(samples.bounds[task], np.float64)
        span = slice(int(offsets[i]), int(offsets[i + 1]))
        samples.xyz.append(_dequantise(tensors["xyz"][:, span].T, b[:3], b[3:]))
        samples.rgb.append(np.ascontiguousarray(tensors["rgb"][:, span].T))
        samples.proprio.append(tensors["proprio"][i])
        samples.target_position.append(tensors["target_position"][i])
        samples.target_quaternion.append(tensors["target_quaternion"][i])
        samples.target_gripper_open.append(bool(tensors["target_gripper_open"][i]))
        samples.target_ignore_collisions.append(bool(tensors["target_ignore_collisions"][i]))
        samples.task_index.append(int(tensors["task_index"][i]))
        samples.instruction_index.append(int(tensors["instruction_index"][i]))
        samples.episode_index.append(int(tensors["episode_index"][i]))
        samples.keyframe_start.append(bool(tensors["keyframe_start"][i]))
        samples.keyframe_index.append(int(keyframe_index[i]))
        samples.final_keyframe.append(bool(final_keyframe[i]))
    embeddings = {t: torch.from_numpy(tensors["lang"][u]) for u, t in enumerate(samples.instructions)}
    return samples, embeddings
