"""Does the instruction encoder itself tell a held-out paraphrase's variation apart? Each paraphrase, filled in for
every variation, against every trained phrasing of the task: is the nearest one (cosine of the mean of the token
embeddings the policy reads, `rvt2cli.model.language.embed_instructions`: all-MiniLM-L6-v2's sentence embedding)
a phrasing of the same variation?

    rvt2 diagnose paraphrase-neighbours [--tasks a,b | --task-set rlbench18]

No checkpoint: the question is the encoder's, before any training. A paraphrase whose words lie nearest another
variation's gives the policy a reason to go there; on rvt2-18 the two paraphrases the model misreads in closed
loop are two of the four so misplaced (docs/RESULTS.md, "Language"). The same table for another encoder is the
offline half of comparing the two.
"""

import torch

from rvt2cli.errors import UserError
from rvt2cli.model.config import RVT2
from rvt2cli.model.language import embed_instructions
from rvt2cli.tasks import get_task


def sentence_embeddings(texts: list[str]) -> torch.Tensor:
    """[len(texts), EMBED_DIM], unit length: the mean of each text's token embeddings (its padding left out)."""
    tokens = embed_instructions(texts, RVT2.lang_tokens)  # the paper configuration's 77 positions
    present = tokens.abs().sum(dim=-1, keepdim=True) > 0
    mean = (tokens * present).sum(dim=1) / present.sum(dim=1).clamp(min=1)
    return torch.nn.functional.normalize(mean, dim=-1)


def task_rows(task) -> list[dict]:
    """One row per paraphrase template of `task`: its variations placed nearest their own, and those that are not."""
    trained = [(v, t.format(**task.variation_values(v))) for v in range(task.num_variations) for t in task.instructions]
    reference = sentence_embeddings([text for _, text in trained])
    rows = []
    for template in task.paraphrases:
        texts = [template.format(**task.variation_values(v)) for v in range(task.num_variations)]
        nearest = (sentence_embeddings(texts) @ reference.T).argmax(dim=1).tolist()
        misplaced = [{"variation": v, "paraphrase": text, "nearest": trained[n][1], "nearest_variation": trained[n][0]}
                     for v, (text, n) in enumerate(zip(texts, nearest)) if trained[n][0] != v]
        rows.append({"task": task.name, "paraphrase": template, "variations": task.num_variations,
                     "nearest_own": task.num_variations - len(misplaced), "misplaced": misplaced})
    return rows


def report(task_names) -> dict:
    tasks = [get_task(name) for name in task_names]
    asked = [t for t in tasks if t.paraphrases and t.num_variations > 1]
    if not asked:
        raise UserError(f"none of {', '.join(task_names)} has held-out paraphrases and several variations; "
                        "give tasks that do (e.g. --task-set rlbench18)")
    return {"tasks": [t.name for t in asked], "rows": [row for task in asked for row in task_rows(task)]}


def markdown(report: dict) -> str:
    lines = ["each held-out paraphrase against the task's trained phrasings (the encoder's sentence embedding)", "",
             "| task | paraphrase | variations nearest their own | a misplaced one: nearest trained phrasing |",
             "|---|---|---|---|"]
    for row in report["rows"]:
        example = row["misplaced"][0] if row["misplaced"] else None
        shown = f'"{example["paraphrase"]}" -> "{example["nearest"]}"' if example else ""
        lines.append(f"| {row['task']} | {row['paraphrase']} | {row['nearest_own']}/{row['variations']} | {shown} |")
    return "\n".join(lines) + "\n"
