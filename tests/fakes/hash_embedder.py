"""A deterministic bag-of-words embedder for tests that need no model.

Each word maps to a fixed random unit vector (seeded by its hash); a text is
the normalised sum of its words, so texts sharing words are similar. It is an
``Embedder`` and counts the texts of each batch it encodes.
"""

from __future__ import annotations

import hashlib
import re

import numpy as np

from services.embedding.models.base import Embedder


class HashEmbedder(Embedder):
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

    def _encode(self, batch: list[str]) -> np.ndarray:
        self.calls.append(len(batch))
        out = np.zeros((len(batch), self._dim), dtype=np.float32)
        for i, text in enumerate(batch):
            words = re.findall(r"[a-z0-9]+", text.lower()) or ["<empty>"]
            vec = sum(self._word(w) for w in words)
            out[i] = vec / np.linalg.norm(vec)
        return out
