"""Where does stage 2 see nothing? A checkpoint on recorded demos: at each keyframe start (the observations a
closed loop makes), stage 1's and stage 2's error against the demo's next keyframe and how many cloud points
lie in stage 2's zoomed box around stage 1's point, then the error of the prediction that keeps stage 1's point
where that box holds fewer than N points (`rvt2 eval --stage2-min-points N`).

    rvt2 diagnose stage2-blind --checkpoint RUN DEMOS... [--min-points 200] [--device cuda] [--json FILE]

Stage 2 renders only +-(workspace half extent / zoom) around stage 1's point, +-10 cm for `rvt2` in the 0.8 m
workspace. stack_blocks carries each block 12 cm above the tower, so the box around that keyframe ends 2 cm above
the tower's top and holds almost nothing; stage 2 then places the keyframe by nothing it can see. The policy
here is the one `rvt2 eval` runs (`predict`, the same box and count).
"""

from collections import defaultdict

import numpy as np


def keyframe_starts(checkpoint: str, demos, device: str = "cpu", batch_size: int = 8) -> list[dict]:
    """One row per keyframe start: task, keyframe index, points in stage 2's box, stage 1's and stage 2's error (mm)."""
    from rvt2cli.eval.offline import load_demos_for
    from rvt2cli.model.language import InstructionCache
    from rvt2cli.model.policy import points_in_box
    from rvt2cli.train.metrics import predict_batches

    loaded = load_demos_for(checkpoint, demos, device=device, progress=False, stage2_min_points=0)
    policy, ckpt, samples = loaded.policy, loaded.checkpoint, loaded.samples
    packed = loaded.pack(InstructionCache(policy.cfg.lang_tokens, ckpt.instruction_embeddings)(samples.instructions), device)
    rows = []
    starts = np.flatnonzero(packed.keyframe_start)
    for idx, batch, pred in predict_batches(policy, packed, starts, batch_size):
        mm = np.asarray(batch.half) * 1000.0
        stage1 = (pred.stage1_position - batch.tcp_position).norm(dim=-1).cpu().numpy() * mm
        stage2 = (pred.position - batch.tcp_position).norm(dim=-1).cpu().numpy() * mm
        points = points_in_box(batch.obs, pred.stage1_position, 1.0 / policy.cfg.zoom).cpu().numpy()
        for j, k in enumerate(idx):
            rows.append({"task": samples.tasks[packed.task[k]], "keyframe": int(packed.keyframe_index[k]),
                         "points": int(points[j]), "stage1_mm": float(stage1[j]), "stage2_mm": float(stage2[j])})
    return rows


def with_min_points(rows: list[dict], min_points: int) -> list[dict]:
    """The rows with `kept_mm`: the prediction's error when stage 1's point is kept below `min_points`."""
    return [r | {"kept_mm": r["stage1_mm"] if r["points"] < min_points else r["stage2_mm"]} for r in rows]


def table(rows: list[dict], min_points: int) -> list[str]:
    """Per task and keyframe index: starts, median points in the box, and the errors' medians."""
    groups = defaultdict(list)
    for r in rows:
        groups[(r["task"], r["keyframe"])].append(r)
    lines = [f"| task | keyframe | starts | points in stage 2's box (median) | stage 1 mm | stage 2 mm | "
             f"stage 1's point kept below {min_points} points, mm |", "|---|---|---|---|---|---|---|"]
    for (task, keyframe), group in sorted(groups.items()):
        med = {k: float(np.median([r[k] for r in group])) for k in ("points", "stage1_mm", "stage2_mm", "kept_mm")}
        lines.append(f"| {task} | {keyframe} | {len(group)} | {med['points']:.0f} | {med['stage1_mm']:.1f} | "
                     f"{med['stage2_mm']:.1f} | {med['kept_mm']:.1f} |")
    everything = {k: float(np.median([r[k] for r in rows])) for k in ("stage1_mm", "stage2_mm", "kept_mm")}
    blind = sum(r["points"] < min_points for r in rows)
    lines.append(f"| **all** | | {len(rows)} ({blind} below {min_points} points) | | {everything['stage1_mm']:.1f} | "
                 f"{everything['stage2_mm']:.1f} | {everything['kept_mm']:.1f} |")
    return lines


def report(checkpoint: str, demos, min_points: int = 200, device: str = "cpu", batch_size: int = 8) -> dict:
    rows = with_min_points(keyframe_starts(checkpoint, demos, device, batch_size), min_points)
    return {"checkpoint": str(checkpoint), "demos": [str(d) for d in demos], "min_points": min_points,
            "table": table(rows, min_points), "rows": rows}


def markdown(report: dict) -> str:
    return "\n".join([f"stage 2's box at keyframe starts: {report['checkpoint']}", "", *report["table"]]) + "\n"
