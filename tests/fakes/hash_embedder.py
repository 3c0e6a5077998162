"""A deterministic bag-of-words embedder for tests that need no model.

Each word maps to a fixed random unit vector (seeded by its hash); a text is
the normalised sum of its words, so texts sharing words are similar. It
satisfies the ``Embedder`` protocol and counts its calls.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Callable, Sequence

import numpy as np


class HashEmbedder:
    def __init__(self, name: str = "test/hash-embedder", dim: int = 64) -> None:
        self._name = name
        self._dim = dim
        self.calls: list[int] = []

    @property
    def name(self) -> str:
        return self._name

    @property
    def dim(self) -> int:
        return self._dim

    def _word(self, word: str) -> np.ndarray:
        seed = int.from_bytes(hashlib.sha256(word.encode()).digest()[:8], "little")
        return np.random.default_rng(seed).standard_normal(self._dim)

    def embed(self, texts: Sequence[str], *, batch_size: int = 64,
              progress: Callable[[int, int], None] | None = None,
              show_progress_bar: bool = False) -> np.ndarray:
        self.calls.append(len(texts))
        out = np.zeros((len(texts), self._dim), dtype=np.float32)
        for i, text in enumerate(texts):
            words = re.findall(r"[a-z0-9]+", text.lower()) or ["<empty>"]
            vec = sum(self._word(w) for w in words)
            out[i] = vec / np.linalg.norm(vec)
            if progress is not None and (i + 1) % batch_size == 0:
                progress(i + 1, len(texts))
        if progress is not None:
            progress(len(texts), len(texts))
        return out
