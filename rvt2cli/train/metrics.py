"""How close a policy's predictions are to the keyframes, in millimetres and degrees: the offline
precision that `rvt2 train` reports on its held-out episodes and `rvt2 eval --offline` on any
recorded demos, without a simulator.

Per sample: the translation error of stage 1 (the coarse point) and of stage 2 (the final point), the
rotation error (geodesic angle between the predicted Euler-bin centre and the true orientation),
and whether the gripper state and the collision flag are right. Summaries give the median, p90 and
mean, overall, per task, per (task, keyframe index) (keyframe 0 = the first of an episode), and per
task for the episodes' final keyframes (the insertion, the placement: where precision decides).
Per task again for the keyframe-start observations alone (frame 0 and each keyframe's frame): a
closed loop observes the scene only there, while the samples between keyframes (the demo
augmentation) are mostly easier, mid-motion, with the gripper already turned towards its goal.
"""

from dataclasses import dataclass

import numpy as np
import torch

from rvt2cli.model.rotation import angle_between
from rvt2cli.train.batches import make_batch
from rvt2cli.train.packed import PackedSamples


@dataclass
class Scores:
    """Per-sample errors of one policy on a set of packed samples."""

    stage1_mm: np.ndarray
    stage2_mm: np.ndarray       # the final position (stage 1's for one-stage configs)
    rotation_deg: np.ndarray
    gripper_ok: np.ndarray      # bool
    collision_ok: np.ndarray    # bool
    task: np.ndarray            # task index per sample
    keyframe_index: np.ndarray  # -1: unknown
    final: np.ndarray           # bool: the target is its episode's last keyframe (an insertion, a placement)
    start: np.ndarray           # bool: observed at frame 0 or at a keyframe, as a closed loop observes

    def __len__(self) -> int:
        return len(self.stage2_mm)

    def subset(self, mask: np.ndarray) -> "Scores":
        return Scores(*(getattr(self, f)[mask] for f in self.__dataclass_fields__))


@torch.no_grad()
def predict_batches(policy, packed: PackedSamples, indices=None, batch_size: int = 8, autocast: bool = False):
    """(indices, batch, prediction) for the packed samples at `indices` (all by default), `batch_size` at a
    time, the policy in eval mode (no augmentation) and put back as it was when the last batch is done."""
    indices = np.arange(len(packed)) if indices is None else np.asarray(indices)
    was_training = policy.training
    policy.eval()
    for start in range(0, len(indices), batch_size):
        idx = indices[start:start + batch_size]
        batch = make_batch(packed, idx, policy.cfg)
        with torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=autocast):
            pred = policy.predict(batch.obs)
        yield idx, batch, pred
    policy.train(was_training)


def score_predictions(policy, packed: PackedSamples, indices=None, batch_size: int = 8, autocast: bool = False,
                      progress=None) -> Scores:
    """Run the policy on every sample (no augmentation) and measure its errors. `progress(n)` is called
    after each batch with the number of samples done in it."""
    parts: dict[str, list] = {f: [] for f in Scores.__dataclass_fields__}
    for idx, batch, pred in predict_batches(policy, packed, indices, batch_size, autocast):
        metres = batch.half[:, None] * 1000.0
        parts["stage1_mm"].append((pred.stage1_position.float() - batch.tcp_position).norm(dim=-1).cpu().numpy() * metres[:, 0])
        parts["stage2_mm"].append((pred.position.float() - batch.tcp_position).norm(dim=-1).cpu().numpy() * metres[:, 0])
        parts["rotation_deg"].append(angle_between(pred.quaternion.float().cpu().numpy(), batch.quaternion))
        parts["gripper_ok"].append((pred.gripper_open.long() == batch.gripper).cpu().numpy())
        parts["collision_ok"].append((pred.ignore_collisions.long() == batch.collision).cpu().numpy())
        parts["task"].append(packed.task[idx])
        parts["keyframe_index"].append(packed.keyframe_index[idx])
        parts["final"].append(packed.final_keyframe[idx])
        parts["start"].append(packed.keyframe_start[idx])
        if progress:
            progress(len(idx))
    return Scores(**{k: np.concatenate(v) if v else np.zeros(0) for k, v in parts.items()})


def _stats(values: np.ndarray) -> dict:
    if len(values) == 0:
        return {"median": None, "p90": None, "mean": None}
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)), "mean": float(np.mean(values))}


def summarize(scores: Scores) -> dict:
    return {"samples": len(scores), "stage1_mm": _stats(scores.stage1_mm), "stage2_mm": _stats(scores.stage2_mm),
            "rotation_deg": _stats(scores.rotation_deg),
            "gripper_accuracy": float(scores.gripper_ok.mean()) if len(scores) else None,
            "collision_accuracy": float(scores.collision_ok.mean()) if len(scores) else None}


def _per_keyframe(scores: Scores) -> dict[str, dict]:
    """Summaries per known keyframe index ("0", "1", ...)."""
    return {str(k): summarize(scores.subset(scores.keyframe_index == k))
            for k in sorted(set(scores.keyframe_index.tolist())) if k >= 0}


def precision_report(scores: Scores, task_names: list[str]) -> dict:
    """Overall, per task, and per task and keyframe index."""
    report = {"overall": summarize(scores), "tasks": {}}
    for t in sorted(set(scores.task.tolist())):
        of_task = scores.subset(scores.task == t)
        entry = summarize(of_task)
        entry["keyframes"] = _per_keyframe(of_task)
        if of_task.final.any():
            entry["final_keyframe"] = summarize(of_task.subset(of_task.final))
        if of_task.start.any():
            starts = of_task.subset(of_task.start)
            entry["starts"] = summarize(starts)
            entry["start_keyframes"] = _per_keyframe(starts)
        report["tasks"][task_names[t]] = entry
    return report


def task_rows(entry: dict) -> list[tuple[str, dict]]:
    """A task's summaries as (label, summary) rows, in the order tables show them: all, each keyframe,
    the final keyframe, then the keyframe starts alone ("starts", "2 start", ...)."""
    rows = [("all", entry), *entry["keyframes"].items()]
    if "final_keyframe" in entry:
        rows.append(("final", entry["final_keyframe"]))
    if "starts" in entry:
        rows += [("starts", entry["starts"]), *((f"{k} start", s) for k, s in entry["start_keyframes"].items())]
    return rows


def headline(s: dict) -> dict:
    """A summary's headline numbers as one flat dict (as TensorBoard and the progress line show them)."""
    return {"samples": s["samples"], "translation_mm": s["stage2_mm"]["mean"], "translation_mm_median": s["stage2_mm"]["median"],
            "translation_mm_p90": s["stage2_mm"]["p90"], "stage1_mm_median": s["stage1_mm"]["median"],
            "rotation_deg": s["rotation_deg"]["mean"], "rotation_deg_median": s["rotation_deg"]["median"],
            "gripper_accuracy": s["gripper_accuracy"], "collision_accuracy": s["collision_accuracy"]}


def prediction_errors(policy, packed: PackedSamples, indices=None, batch_size: int = 8, autocast: bool = False) -> dict:
    """The headline numbers of a policy's predictions on packed samples."""
    return headline(summarize(score_predictions(policy, packed, indices, batch_size, autocast)))
