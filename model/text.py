"""Prompt encoders producing (B, L, text_dim) features for the transformer's cross-attention.

- :class:`HashedTextEncoder` (tiny): lower-cased word tokens hashed (blake2b, stable across runs
  and machines) into a trainable embedding table plus a learned position table; padding rows are
  exact zeros, like Wan's zero-padded UMT5 context. The empty prompt is all zeros, which is also
  the "null" condition used for classifier-free guidance.
- :class:`PrecomputedTextEncoder` (Wan presets): UMT5-XXL features precomputed elsewhere, read
  from ``<folder>/<prompt_key(prompt)>.pt`` (a (L, 4096) tensor) or given per sample.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import torch
from torch import nn

from egosim.model.errors import MissingEmbeddingError, ModelConfigError

_TOKEN = re.compile(r"[a-z0-9]+")


def prompt_key(prompt: str) -> str:
    """File stem of a prompt's precomputed embedding (first 16 hex digits of its sha256)."""
    return hashlib.sha256(prompt.encode("utf-8")).hexdigest()[:16]


def pad_tokens(x: torch.Tensor, length: int) -> torch.Tensor:
    """Zero-pad or truncate a (L, D) feature sequence to ``length`` rows."""
    out = x.new_zeros(length, x.shape[1])
    n = min(length, x.shape[0])
    out[:n] = x[:n]
    return out


class HashedTextEncoder(nn.Module):
    """Trainable hashed-word embedding (a stand-in text encoder that needs no download)."""

    def __init__(self, text_dim: int, max_tokens: int, vocab_size: int) -> None:
        super().__init__()
        self.max_tokens = max_tokens
        self.vocab_size = vocab_size
        # N(0, 1) rows give unit-scale features, matching what the Wan text projection expects
        # (PixArtAlphaTextProjection is followed by layer norms); positions start small.
        self.tokens = nn.Embedding(vocab_size, text_dim)
        nn.init.normal_(self.tokens.weight, std=1.0)
        self.positions = nn.Parameter(torch.randn(max_tokens, text_dim) * 0.02)

    def token_ids(self, prompt: str) -> list[int]:
        """Hash bucket of each word of ``prompt`` (at most ``max_tokens``)."""
        words = _TOKEN.findall(prompt.lower())[: self.max_tokens]
        return [
            int.from_bytes(hashlib.blake2b(w.encode(), digest_size=8).digest(), "little")
            % self.vocab_size
            for w in words
        ]

    def forward(self, prompts: list[str]) -> torch.Tensor:
        """Prompts -> (B, max_tokens, text_dim); rows past the last word are zeros."""
        device = self.tokens.weight.device
        ids = torch.zeros(len(prompts), self.max_tokens, dtype=torch.long, device=device)
        valid = torch.zeros(len(prompts), self.max_tokens, 1, device=device)
        for i, p in enumerate(prompts):
            tok = self.token_ids(p)
            ids[i, : len(tok)] = torch.tensor(tok, dtype=torch.long)
            valid[i, : len(tok)] = 1.0
        return (self.tokens(ids) + self.positions) * valid  # (B, L, D)


class PrecomputedTextEncoder(nn.Module):
    """Reads precomputed UMT5 features: per-sample tensors first, then ``<folder>/<key>.pt``."""

    def __init__(self, text_dim: int, max_tokens: int, folder: str | Path | None = None) -> None:
        super().__init__()
        self.text_dim = text_dim
        self.max_tokens = max_tokens
        self.folder = None if folder is None else Path(folder)

    def lookup(self, prompt: str) -> torch.Tensor:
        """The (L, text_dim) features of ``prompt`` from the folder; empty prompt -> zeros."""
        if prompt == "":
            return torch.zeros(self.max_tokens, self.text_dim)
        if self.folder is None:
            raise MissingEmbeddingError(
                f"no text embedding for prompt {prompt!r}: pass text_embedding in the sample "
                "or a text_embeddings folder"
            )
        path = self.folder / f"{prompt_key(prompt)}.pt"
        if not path.is_file():
            raise MissingEmbeddingError(f"no text embedding for prompt {prompt!r} at {path}")
        return torch.load(path, map_location="cpu", weights_only=True).float()

    def forward(
        self, prompts: list[str], given: list[torch.Tensor | None] | None = None
    ) -> torch.Tensor:
        """Prompts (and optional per-sample tensors) -> (B, max_tokens, text_dim)."""
        given = given or [None] * len(prompts)
        rows = []
        for p, g in zip(prompts, given, strict=True):
            x = self.lookup(p) if g is None else g.float()
            if x.ndim != 2 or x.shape[1] != self.text_dim:
                raise ModelConfigError(
                    f"text embedding for {p!r} must be (L, {self.text_dim}), got {tuple(x.shape)}"
                )
            rows.append(pad_tokens(x, self.max_tokens))
        return torch.stack(rows)
