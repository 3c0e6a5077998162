"""What the detector needs of an embedding model: ``Embedder``, ``Wrapping``, the errors (numpy).

``Embedder`` has a ``name``, a ``dim`` and ``embed``, which batches, reports progress and
L2-normalises what a backend's ``_encode`` returns; ``Wrapping`` is one in front of another;
then ``normalize`` and the errors a backend raises. Numpy only: the backends that load
models or call servers are in ``.embedders`` and ``.onnx_backend``.

Exceptions::

    EmbedderError        a backend failed: HTTP error, timeout, malformed answer,
     |                   a model that does not load, a zero or non-finite vector
     +-- ModelNotFound   no local copy of the model; the message lists every
                         place looked in and how to provide the model
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from types import TracebackType
from typing import Self

import numpy as np

ProgressFn = Callable[[int, int], None]
"""Called as ``progress(done, total)`` after each batch."""


class EmbedderError(Exception):
    """A backend failed: HTTP error, timeout, malformed response, unloadable model."""


class ModelNotFound(EmbedderError):
    """No local copy of the model; the message names every place looked in."""


def normalize(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` scaled to unit L2 norm, as a new float32 C-contiguous array.

    Norms are taken in float64 after scaling by the largest entry, so no input overflows. A 1-D
    array is one row. Raises ``EmbedderError`` on a zero or non-finite row.
    """
    x = np.asarray(v, dtype=np.float64)
    if x.ndim not in (1, 2):
        raise ValueError(f"expected a vector or a 2-D array of rows, got shape {x.shape}")
    bad = ~np.isfinite(x).all(axis=-1)
    if bad.any():
        raise EmbedderError(f"non-finite embedding values in rows {_rows(bad)}")
    scale = np.abs(x).max(axis=-1, keepdims=True, initial=0.0)  # keeps squares finite
    zero = (scale == 0.0).reshape(bad.shape)
    if zero.any():
        raise EmbedderError(f"zero embedding vectors (no direction) in rows {_rows(zero)}")
    x = x / scale
    return np.ascontiguousarray(x / np.linalg.norm(x, axis=-1, keepdims=True), dtype=np.float32)


def _rows(mask: np.ndarray | np.bool_) -> str:
    idx = np.flatnonzero(mask)
    shown = ", ".join(str(i) for i in idx[:10])
    return shown + (f", ... ({idx.size} in all)" if idx.size > 10 else "")


# --- shared batching ---------------------------------------------------------


def _check_texts(texts: Sequence[str]) -> list[str]:
    if isinstance(texts, str | bytes):
        raise TypeError("texts must be a sequence of str, not a single string")
    items = list(texts)
    for i, text in enumerate(items):
        if not isinstance(text, str):
            raise TypeError(f"texts[{i}] is {type(text).__name__}, expected str")
    return items


def _embed_in_batches(
    texts: Sequence[str],
    encode: Callable[[list[str]], np.ndarray],
    *,
    batch_size: int,
    progress: ProgressFn | None,
    show_progress_bar: bool,
    desc: str,
) -> list[np.ndarray]:
    """Runs ``encode`` on consecutive batches; reports progress after each one."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    items = _check_texts(texts)
    total = len(items)
    parts: list[np.ndarray] = []
    with _progress_bar(total, show_progress_bar, desc) as advance:
        for start in range(0, total, batch_size):
            batch = items[start : start + batch_size]
            parts.append(encode(batch))
            advance(len(batch))
            if progress is not None:
                progress(start + len(batch), total)
    return parts


@contextmanager
def _progress_bar(total: int, enabled: bool, desc: str) -> Iterator[Callable[[int], object]]:
    if not enabled:
        yield lambda n: None
        return
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit="text", file=sys.stderr) as bar:
        yield bar.update


def _stack(parts: list[np.ndarray], dim: int, name: str) -> np.ndarray:
    if not parts:
        return np.zeros((0, dim), dtype=np.float32)
    try:
        return normalize(np.concatenate(parts, axis=0))
    except EmbedderError as exc:
        raise EmbedderError(f"{name}: {exc}") from None


class Closing:
    """``with x:`` closes ``x`` at the end."""

    def close(self) -> None:
        """Release what is held (nothing by default)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class Embedder(Closing):
    """What the vector cache needs from an embedding backend. A backend gives its
    ``name`` and ``dim`` and encodes one batch (``_encode``); ``embed`` batches, reports
    progress and L2-normalises. (A base class, not a runtime-checkable Protocol: on
    Python 3.11 ``isinstance`` would read ``dim``, an HTTP request for ``OpenAIEmbedder``.)"""

    @property
    def name(self) -> str:
        """The model id a cache pins, e.g. ``sentence-transformers/all-MiniLM-L6-v2``."""
        raise NotImplementedError

    @property
    def dim(self) -> int:
        raise NotImplementedError

    def _encode(self, batch: list[str]) -> np.ndarray:
        raise NotImplementedError

    def embed(
        self,
        texts: Sequence[str],
        *,
        batch_size: int = 64,
        progress: ProgressFn | None = None,
        show_progress_bar: bool = False,
    ) -> np.ndarray:
        """``(len(texts), dim)`` float32, C-contiguous, rows of unit L2 norm."""
        parts = _embed_in_batches(
            texts, self._encode, batch_size=batch_size, progress=progress,
            show_progress_bar=show_progress_bar, desc=self.name,
        )
        return _stack(parts, self.dim if not parts else parts[0].shape[1], self.name)


class Wrapping(Embedder):
    """An embedder in front of another, ``inner``: its ``name``, ``dim`` and ``close`` are
    the inner's; a subclass changes how ``embed`` gets there (counted, memoised)."""

    def __init__(self, inner: Embedder) -> None:
        self.inner = inner

    @property
    def name(self) -> str:
        return self.inner.name

    @property
    def dim(self) -> int:
        return self.inner.dim

    def close(self) -> None:
        self.inner.close()
