"""Embed every task's instructions (of every variation, and the held-out paraphrases `rvt2 eval
--paraphrases` uses) into one file, for machines without the text encoder:
RVT2_EMBEDDINGS=FILE makes rvt2 read them from there (rvt2cli/model/language.py).

    python scripts/embed_instructions.py --out .gpu/embeddings.safetensors
"""

import argparse

from rvt2cli.model.config import CONFIGS
from rvt2cli.model.language import save_embeddings
from rvt2cli.tasks import all_tasks

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--out", required=True)
args = parser.parse_args()
texts = sorted({text for task in all_tasks().values() for text in task.all_instructions() + task.all_paraphrases()})
save_embeddings(texts, args.out, max(c.lang_tokens for c in CONFIGS.values()))
print(f"{args.out}: {len(texts)} instructions")
