"""``hash``: a tiny deterministic text encoder for unit tests (no weights, no downloads)."""

from __future__ import annotations

import hashlib
import re

import torch
from torch import Tensor

from omg.registry import TEXT_ENCODERS
from omg.text.base import TextEncoder

START, END = 0, 1  # reserved table rows; hashed words use rows 2..vocab_size+1


@TEXT_ENCODERS.register("hash")
class HashTextEncoder(TextEncoder):
    """Test-only encoder: words hashed (blake2b) into a seeded random table, scaled by position.

    The end token holds the mean of the sentence's token features, so that, as with CLIP's
    EOT, ``eot_embedding()`` tells sentences apart.
    """

    name = "hash"

    def __init__(self, dim: int = 64, max_tokens: int = 32, vocab_size: int = 4096, seed: int = 0,
                 cache_size: int = 100_000):
        super().__init__(cache_size)
        self.dim, self.max_tokens, self.vocab_size = dim, max_tokens, vocab_size
        # explicit CPU device: deterministic even when built under a meta/cuda device context
        g = torch.Generator().manual_seed(seed)
        self.register_buffer("table", torch.randn(vocab_size + 2, dim, generator=g, device="cpu"), persistent=False)
        # multiplicative, so that the mean at the end token depends on word order
        self.register_buffer("pos", 1 + 0.5 * torch.randn(max_tokens, dim, generator=g, device="cpu"), persistent=False)
        self._freeze()

    def token_ids(self, text: str) -> list[int]:
        words = re.findall(r"[\w']+", text.lower())
        if len(words) + 2 > self.max_tokens:
            self._warn_truncated(text)
            words = words[: self.max_tokens - 2]
        return [START] + [2 + _stable_hash(w) % self.vocab_size for w in words] + [END]

    def token_spans(self, text: str) -> list[tuple[int, int]]:
        words = [m.span() for m in re.finditer(r"[\w']+", text)][: self.max_tokens - 2]
        return [(0, 0), *words, (0, 0)]

    def _encode(self, texts: list[str]) -> list[Tensor]:
        out = []
        for text in texts:
            ids = torch.tensor(self.token_ids(text), device=self.table.device)
            x = self.table[ids] * self.pos[: len(ids)]  # (n, D)
            x[-1] = x.mean(0)
            out.append(x)
        return out


def _stable_hash(word: str) -> int:
    # Python's hash() is salted per process; blake2b is the same everywhere
    return int.from_bytes(hashlib.blake2b(word.encode(), digest_size=8).digest(), "little")
