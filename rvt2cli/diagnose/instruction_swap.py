"""Does the instruction decide where the policy goes? Recorded demos, each observation predicted under its own
instruction and under every other variation's (the same template), without a simulator.

    rvt2 diagnose instruction-swap --checkpoint RUN DEMOS... [--device cuda] [--decides-mm 20] [--json FILE]

On rvt2-18 only the instruction tells a task's variations apart (which colour, which object, which slot). A
closed-loop `wrong_target` failure is either the policy not reading the words (its prediction barely moves
when they change) or it reading them and going wrong anyway. Per task and keyframe index, the observations
at the previous keyframe ("start": what a closed loop sees) apart from those on the way:

- `error_mm`: the own instruction's stage-2 error against the demo's next keyframe (as `rvt2 eval --offline`);
- `moved_mm`: how far the other instructions move the prediction (median over observations of the median
  distance from the own instruction's prediction);
- `deciding`: observations whose predictions spread over more than --decides-mm (the words choose a place
  there; elsewhere every variation goes to the same place, such as grasping the one block), and `chosen`:
  the share of those where the own instruction's prediction is the one nearest the demo's keyframe (within
  5 mm of the nearest: two variations may rightly share a place).
"""

import dataclasses
from collections import defaultdict

import numpy as np
import torch

from rvt2cli.eval.offline import load_demos_for
from rvt2cli.model.language import InstructionCache
from rvt2cli.tasks import get_task
from rvt2cli.train.metrics import predict_batches


def alternatives(task_name: str, instruction: str) -> list[str]:
    """The instruction first, then the same template filled with each other variation's values."""
    task = get_task(task_name)
    for template in task.instructions:
        texts = [template.format(**task.variation_values(v)) for v in range(task.num_variations)]
        if instruction in texts:
            return [instruction] + [t for t in dict.fromkeys(texts) if t != instruction]
    return [instruction]   # not one of the task's own phrasings (a paraphrase): nothing to swap


def predicted_positions(policy, packed, batch_size: int, autocast: bool) -> np.ndarray:
    """Stage-2 positions (metres, world frame) the policy predicts for every packed sample."""
    out = []
    with torch.no_grad():
        for idx, _, pred in predict_batches(policy, packed, batch_size=batch_size, autocast=autocast):
            tasks = packed.task[idx]
            out.append(pred.position.float().cpu().numpy() * packed.half[tasks][:, None] + packed.center[tasks])
    return np.concatenate(out)


def swap_report(checkpoint: str, demos, device: str = "cpu", batch_size: int = 8, decides_mm: float = 20.0,
                near_mm: float = 5.0) -> dict:
    loaded = load_demos_for(checkpoint, demos, device=device, progress=False)
    policy, ckpt, paths, samples = loaded.policy, loaded.checkpoint, loaded.paths, loaded.samples
    # each sample's instructions, its own first: positions[k, r] is sample r predicted under its k-th
    choices = [alternatives(samples.tasks[samples.task_index[i]], samples.instructions[samples.instruction_index[i]])
               for i in range(len(samples))]
    texts = sorted({t for c in choices for t in c})
    lang = InstructionCache(policy.cfg.lang_tokens, ckpt.instruction_embeddings)(texts)
    base = loaded.pack(lang, device)
    autocast = torch.device(device).type == "cuda"
    most = max(len(c) for c in choices)
    positions = np.full((most, len(samples), 3), np.nan)
    slot = {text: i for i, text in enumerate(texts)}   # a text's row in `lang`
    for k in range(most):   # round k: every sample under its k-th instruction (its own where it has fewer)
        instruction = torch.as_tensor([slot[c[min(k, len(c) - 1)]] for c in choices], device=base.instruction.device)
        predicted = predicted_positions(policy, dataclasses.replace(base, instruction=instruction), batch_size, autocast)
        has = [i for i, c in enumerate(choices) if k < len(c)]
        positions[k, has] = predicted[has]
    target = base.target_position
    own = positions[0]
    error = np.linalg.norm(own - target, axis=-1) * 1000
    moved = np.linalg.norm(positions[1:] - own[None], axis=-1) * 1000          # [alternatives, samples]
    to_target = np.linalg.norm(positions - target[None], axis=-1) * 1000       # [alternatives + 1, samples]
    spread = np.nanmax(moved, axis=0, initial=0.0)
    groups = defaultdict(list)
    for i in range(len(samples)):   # observations at a keyframe (what a closed loop sees) apart from those between
        groups[(samples.tasks[samples.task_index[i]], int(samples.keyframe_index[i]), bool(samples.keyframe_start[i]))].append(i)
    rows = []
    for (task, keyframe, start), members in sorted(groups.items()):
        deciding = [i for i in members if spread[i] > decides_mm]
        rows.append({"task": task, "keyframe": keyframe, "start": start, "samples": len(members),
                     "alternatives": max(len(choices[i]) for i in members) - 1,   # 0 for a phrasing naming no value
                     "error_mm": float(np.median(error[members])),
                     "moved_mm": float(np.median([np.nanmedian(moved[:, i]) for i in members])) if most > 1 else 0.0,
                     "deciding": len(deciding),
                     "chosen": (float(np.mean([to_target[0, i] <= np.nanmin(to_target[1:, i]) + near_mm for i in deciding]))
                                if deciding else None),
                     "own_mm": [float(error[i]) for i in members],
                     "others_mm": [[float(d) for d in to_target[1:, i]] for i in members]})
    return {"checkpoint": str(ckpt.path), "episodes": len(paths), "decides_mm": decides_mm, "rows": rows}


def markdown(report: dict) -> str:
    lines = [f"instruction swap: {report['checkpoint']}, {report['episodes']} episodes; deciding: predictions "
             f"spread over {report['decides_mm']:.0f} mm", "",
             "| task | keyframe | samples | other instructions | error mm | moved mm | deciding | own nearest |",
             "|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        chosen = "-" if r["chosen"] is None else f"{r['chosen']:.0%}"
        lines.append(f"| {r['task']} | {r['keyframe']}{' start' if r['start'] else ''} | {r['samples']} | {r['alternatives']} | {r['error_mm']:.1f} | "
                     f"{r['moved_mm']:.1f} | {r['deciding']} | {chosen} |")
    return "\n".join(lines) + "\n"
