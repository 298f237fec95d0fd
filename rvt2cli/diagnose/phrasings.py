"""Does the phrasing matter? Recorded demos, each keyframe-start observation (what a closed loop sees)
predicted under every phrasing of its own variation: the task's trained templates and its held-out
paraphrases, without a simulator.

    rvt2 diagnose phrasings --checkpoint RUN DEMOS... [--device cuda] [--json FILE]

`rvt2 eval --paraphrases` says which phrasings fail closed loop ("Success per phrasing"); this says where.
Per task, keyframe and phrasing: the stage-2 error against the demo's next keyframe (median over the
observations), beside the same observations under the trained phrasings. A phrasing the policy misreads
moves the keyframes its words decide (which drawer, which block, which button next) and leaves the rest.
"""

import dataclasses
from collections import defaultdict

import numpy as np
import torch

from rvt2cli.diagnose.instruction_swap import predicted_positions
from rvt2cli.eval.offline import load_demos_for
from rvt2cli.model.language import InstructionCache
from rvt2cli.tasks import get_task


def phrasings(task_name: str, instruction: str) -> tuple[int, list[tuple[str, str, bool]]]:
    """The variation `instruction` names and each of its phrasings: (template, text, held out), trained ones
    first. (-1, []) where the instruction is no trained phrasing of the task's (a user's own words)."""
    task = get_task(task_name)
    v = task.variation_of(instruction)
    if v is None:
        return -1, []
    values = task.variation_values(v)
    return v, ([(t, t.format(**values), False) for t in task.instructions]
               + [(t, t.format(**values), True) for t in task.paraphrases])


def phrasing_report(checkpoint: str, demos, device: str = "cpu", batch_size: int = 8) -> dict:
    loaded = load_demos_for(checkpoint, demos, device=device, progress=False)
    samples = loaded.samples
    loaded.samples = samples = samples.subset([i for i in range(len(samples)) if samples.keyframe_start[i]])
    task_of = [samples.tasks[samples.task_index[i]] for i in range(len(samples))]
    variation, choices = zip(*(phrasings(task_of[i], samples.instructions[samples.instruction_index[i]])
                               for i in range(len(samples)))) if len(samples) else ((), ())
    texts = sorted({text for c in choices for _, text, _ in c} | set(samples.instructions))
    slot = {text: i for i, text in enumerate(texts)}
    lang = InstructionCache(loaded.policy.cfg.lang_tokens, loaded.checkpoint.instruction_embeddings)(texts)
    base = loaded.pack(lang, device)
    autocast = torch.device(device).type == "cuda"
    target = base.target_position
    errors = defaultdict(list)   # (task, variation, keyframe, template, held out) -> mm per observation
    for k in range(max((len(c) for c in choices), default=0)):   # round k: each sample under its k-th phrasing
        has = [i for i, c in enumerate(choices) if k < len(c)]
        own = torch.as_tensor([slot[choices[i][k][1] if k < len(choices[i]) else samples.instructions[samples.instruction_index[i]]]
                               for i in range(len(samples))], device=base.instruction.device)
        predicted = predicted_positions(loaded.policy, dataclasses.replace(base, instruction=own), batch_size, autocast)
        for i in has:
            template, _, held_out = choices[i][k]
            errors[(task_of[i], variation[i], int(samples.keyframe_index[i]), template, held_out)].append(
                float(np.linalg.norm(predicted[i] - target[i]) * 1000))
    rows = [{"task": task, "variation": v, "keyframe": keyframe, "phrasing": template, "held_out": held_out,
             "samples": len(mm), "error_mm": float(np.median(mm)), "far": sum(e > 20.0 for e in mm)}
            for (task, v, keyframe, template, held_out), mm in sorted(errors.items())]
    return {"checkpoint": str(loaded.checkpoint.path), "episodes": len(loaded.paths), "rows": rows}


def markdown(report: dict) -> str:
    """Per task, variation and keyframe, one column per phrasing of the task (trained first, held out marked *)."""
    lines = [f"phrasings: {report['checkpoint']}, {report['episodes']} episodes; stage-2 error at keyframe starts, "
             "mm (median), and how many observations missed by more than 20 mm; * held out", ""]
    by_task = defaultdict(list)
    for r in report["rows"]:
        by_task[r["task"]].append(r)
    for task, rows in by_task.items():
        templates = list(dict.fromkeys(r["phrasing"] + ("*" if r["held_out"] else "") for r in sorted(rows, key=lambda r: r["held_out"])))
        lines += [f"**{task}**: " + "; ".join(f"({n + 1}) {t}" for n, t in enumerate(templates)), "",
                  "| variation | keyframe | samples | " + " | ".join(f"({n + 1})" for n in range(len(templates))) + " |",
                  "|---|---|---|" + "---|" * len(templates)]
        cells = defaultdict(dict)
        for r in rows:
            cells[(r["variation"], r["keyframe"])][r["phrasing"] + ("*" if r["held_out"] else "")] = r
        for (v, keyframe), row in sorted(cells.items()):
            first = next(iter(row.values()))
            lines.append(f"| {v} | {keyframe} | {first['samples']} | " + " | ".join(
                f"{row[t]['error_mm']:.1f} ({row[t]['far']})" if t in row else "-" for t in templates) + " |")
        lines.append("")
    return "\n".join(lines)
