"""`rvt2 eval --offline DEMOS...`: a checkpoint's precision on recorded demos, without a simulator.

The policy predicts the next keyframe from every observation of the episodes (each training sample:
frame 0, every 10th frame and every keyframe), and its prediction is scored against the keyframe the
demo went to next: stage-1 and stage-2 translation error (mm), rotation error (degrees), gripper and
collision-flag accuracy; per task and per keyframe index (`rvt2cli.train.metrics`). It tells in
minutes, in millimetres, whether a training change made the policy more precise, before a
closed-loop evaluation costs simulator hours.
"""

import json
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from rvt2cli.atomic import atomic_open, ensure_folder
from rvt2cli.data.paths import episode_paths
from rvt2cli.data.reader import read_episode_overview
from rvt2cli.errors import UserError
from rvt2cli.model.language import InstructionCache
from rvt2cli.train.packed import pack
from rvt2cli.train.checkpoint import load_policy
from rvt2cli.train.metrics import precision_report, score_predictions, task_rows
from rvt2cli.train.samples import load_samples, trained_instructions

DEFAULT_MAX_POINTS = 50_000


def _cameras(ckpt) -> tuple[str, ...] | None:
    """The cameras the policy was trained with, when every task used the same ones."""
    rigs = {tuple(r.get("cameras") or ()) for r in ckpt.info.get("rigs", {}).values()}
    return next(iter(rigs)) if len(rigs) == 1 and next(iter(rigs)) else None


@dataclass
class DemosForPolicy:
    """A checkpoint's policy and the samples of recorded demos as it sees them (its cameras, its point budget)."""
    policy: object
    checkpoint: object
    paths: list
    samples: object
    max_points: int

    def pack(self, lang, device: str):
        """Every sample, packed in order with these instruction embeddings, as training packs them."""
        return pack(self.samples, list(range(len(self.samples))), lang, self.max_points, torch.device(device), seed=0,
                    aim_offsets=self.checkpoint.aim_offsets)


def load_demos_for(checkpoint: str, demos, device: str = "cpu", progress: bool = True,
                   stage2_min_points: int | None = None) -> DemosForPolicy:
    """The policy of `checkpoint` and every sample of `demos` (failed expert runs too); demos of a task the
    checkpoint was not trained on are one line. `stage2_min_points` overrides the checkpoint's."""
    policy, ckpt = load_policy(checkpoint, device=device, stage2_min_points=stage2_min_points)
    paths = episode_paths(list(demos))
    tasks = sorted({read_episode_overview(p).meta.task for p in paths})
    unknown = [t for t in tasks if t not in ckpt.tasks]
    if unknown:
        raise UserError(f"{ckpt.path}: was not trained on task(s) {', '.join(unknown)} of the demos "
                        f"(it knows {', '.join(ckpt.tasks)}); give demos of those tasks")
    samples = load_samples(paths, include_failures=True, progress=progress, cameras=_cameras(ckpt))
    return DemosForPolicy(policy, ckpt, paths, samples, int(ckpt.training_options.get("max_points") or DEFAULT_MAX_POINTS))


def evaluate_offline(checkpoint: str, demos, out: str | Path | None = None, device: str = "cpu", batch_size: int = 8,
                     progress: bool = True, stage2_min_points: int | None = None) -> dict:
    start = time.perf_counter()
    out = ensure_folder(out) if out is not None else None  # a bad --out is one line, before minutes of work
    loaded = load_demos_for(checkpoint, demos, device=device, progress=progress, stage2_min_points=stage2_min_points)
    policy, ckpt, paths, samples = loaded.policy, loaded.checkpoint, loaded.paths, loaded.samples
    # the words the model was trained to read for each demo's instruction (its first phrasing under --phrasings first)
    texts = trained_instructions(samples, ckpt.training_options.get("phrasings", "demo"))
    packed = loaded.pack(InstructionCache(policy.cfg.lang_tokens, ckpt.instruction_embeddings)(texts), device)
    from tqdm import tqdm

    with tqdm(total=len(packed), desc="offline", unit="obs", disable=not progress, dynamic_ncols=True) as bar:
        scores = score_predictions(policy, packed, batch_size=batch_size, autocast=torch.device(device).type == "cuda",
                                   progress=bar.update)
    report = {"checkpoint": str(ckpt.path), "step": ckpt.info.get("step"), "episodes": len(paths),
              "stage2_min_points": policy.cfg.stage2_min_points,
              "seconds": time.perf_counter() - start, **precision_report(scores, samples.tasks)}
    if out is not None:
        with atomic_open(out / "offline.json", "w") as f:
            json.dump(report, f, indent=2)
        with atomic_open(out / "offline.md", "w") as f:
            f.write(markdown(report))
    return report


def _cell(stats: dict, digits: int = 1) -> str:
    return "-" if stats["median"] is None else f"{stats['median']:.{digits}f} / {stats['p90']:.{digits}f}"


def markdown(report: dict) -> str:
    lines = [f"# Offline precision: {report['checkpoint']} (step {report['step']})", "",
             f"{report['overall']['samples']} observations of {report['episodes']} episodes; errors as median / p90. "
             "Rows \"starts\" and \"K start\": the observations at frame 0 and at each keyframe alone, the only "
             "ones a closed loop makes."
             + (f" Stage 1's point kept where stage 2's box held fewer than {report['stage2_min_points']} points "
                "(the stage 2 column is the prediction)." if report.get("stage2_min_points") else ""), "",
             "| task | keyframe | samples | stage 1 mm | stage 2 mm | rotation deg | gripper | collision flag |",
             "|---|---|---|---|---|---|---|---|"]

    def row(task, keyframe, s):
        lines.append(f"| {task} | {keyframe} | {s['samples']} | {_cell(s['stage1_mm'])} | {_cell(s['stage2_mm'])} | "
                     f"{_cell(s['rotation_deg'])} | {s['gripper_accuracy']:.0%} | {s['collision_accuracy']:.0%} |")

    for task, entry in report["tasks"].items():
        for i, (keyframe, s) in enumerate(task_rows(entry)):
            row(task if i == 0 else "", keyframe, s)
    row("**all**", "", report["overall"])
    return "\n".join(lines) + "\n"


def headline_line(report: dict) -> str:
    s = report["overall"]
    return (f"{s['samples']} observations: stage-2 error {s['stage2_mm']['median']:.1f} mm median "
            f"({s['stage2_mm']['p90']:.1f} p90), stage 1 {s['stage1_mm']['median']:.1f} mm, rotation "
            f"{s['rotation_deg']['median']:.1f} deg, gripper {s['gripper_accuracy']:.0%}, collision flag "
            f"{s['collision_accuracy']:.0%}")

