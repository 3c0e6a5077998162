"""An embedder that counts the texts it embeds on the command's progress line.

The line is :mod:`tools.progress`'s: ``aesop detector eval`` and ``aesop bench detector`` embed
thousands of texts through code that knows nothing of a terminal."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from services.embedding.models.base import Embedder, ProgressFn, Wrapping
from tools.progress import count


class Counted(Wrapping):
    """``inner``, each batch counted on the live line (a log gets no line a batch): the
    texts embedded since this wrapper was made."""

    def __init__(self, inner: Embedder, unit: str = "texts embedded") -> None:
        super().__init__(inner)
        self.unit = unit
        self.done = 0

    def embed(self, texts: Sequence[str], *, batch_size: int = 64,
              progress: ProgressFn | None = None, show_progress_bar: bool = False
              ) -> np.ndarray:
        before = self.done

        def seen(done: int, total: int) -> None:
            self.done = before + done
            count(self.done, None, self.unit)
            if progress is not None:
                progress(done, total)

        return self.inner.embed(texts, batch_size=batch_size, progress=seen,
                                show_progress_bar=show_progress_bar)
