"""Choosing and sharing embedders: a model's name -> the backend that runs it, loaded once.

``load_embedder`` maps a name to its backend (``openai:``, ``onnx:``/``onnx-int8:``, or a
local sentence-transformers model) and ``EmbedderPool`` keeps each loaded model once for
every caller. It sits above both backends' modules (``embedders``, ``onnx_backend``), so
neither imports the other's chooser.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

from . import onnx_backend
from .base import Closing, Embedder, ModelNotFound
from .embedders import (
    DEFAULT_MODEL,
    DEFAULT_OPENAI_BASE_URL,
    OPENAI_PREFIX,
    NotFoundLocally,
    OpenAIEmbedder,
    SentenceTransformerEmbedder,
    is_dir,
    pool_key,
    split_onnx,
)

log = logging.getLogger(__name__)


def load_embedder(
    model: str,
    *,
    openai_base_url: str = DEFAULT_OPENAI_BASE_URL,
    openai_api_key: str | None = None,
    device: str = "cpu",
    hf_cache_dir: str | Path | None = None,
    export_dir: Path | None = None,
    threads: int = 1,
) -> Embedder:
    """``"openai:<name>"`` -> ``OpenAIEmbedder``; ``"onnx:<model>"`` or
    ``"onnx-int8:<model>"`` -> ``OnnxEmbedder`` (exported once into ``export_dir``);
    anything else -> a local ``SentenceTransformerEmbedder`` (``ModelNotFound`` if it is
    not on disk)."""
    onnx = split_onnx(model)
    if onnx is not None:
        return onnx_backend.OnnxEmbedder(
            onnx[0], int8=onnx[1], export_dir=export_dir or onnx_backend.default_export_dir(),
            threads=threads, hf_cache_dir=hf_cache_dir)
    if model.startswith(OPENAI_PREFIX):
        name = model.removeprefix(OPENAI_PREFIX)
        if not name:
            raise ModelNotFound(f"{model!r}: give the model after the prefix, e.g. "
                                "'openai:text-embedding-3-small'")
        return OpenAIEmbedder(name, base_url=openai_base_url, api_key=openai_api_key)
    return SentenceTransformerEmbedder(model, device=device, hf_cache_dir=hf_cache_dir)


class _Slot:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.embedder: Embedder | None = None


class EmbedderPool(Closing):
    """Loads each model once and shares it between callers; thread-safe.

    Two threads asking for the same model wait for one load; different models
    load in parallel. A failed load is not remembered: the next ``get`` retries.
    At most ``max_loaded`` models stay loaded: the least recently used one is let
    go (a caller still holding it finishes with it). A model given as a directory
    must lie inside ``model_dir`` (when one is set): the service's callers name
    models, they do not pick files of the machine.
    """

    def __init__(
        self,
        *,
        openai_base_url: str = DEFAULT_OPENAI_BASE_URL,
        openai_api_key: str | None = None,
        device: str = "cpu",
        hf_cache_dir: str | Path | None = None,
        loader: Callable[[str], Embedder] | None = None,
        model_dir: Path | None = None,
        max_loaded: int = 4,
        export_dir: Path | None = None,
        threads: int = 1,
    ) -> None:
        """``export_dir``: where ONNX exports are kept; ``threads``: per ONNX inference."""
        self._loader = loader or (
            lambda model: load_embedder(
                model, openai_base_url=openai_base_url, openai_api_key=openai_api_key,
                device=device, hf_cache_dir=hf_cache_dir, export_dir=export_dir,
                threads=threads,
            )
        )
        self._lock = threading.Lock()
        self._slots: OrderedDict[str, _Slot] = OrderedDict()  # least recently used first
        self._closed = False
        self._model_dir = model_dir.resolve() if model_dir is not None else None
        self._max_loaded = max_loaded

    def get(self, model: str) -> Embedder:
        self._check_directory(model)
        try:
            return self._get(model)
        except NotFoundLocally as exc:
            if self._model_dir is None:
                raise
            log.info("model %r not loaded: %s", model, exc)  # the details stay here
            raise ModelNotFound(self._refusal(model)) from None

    def _refusal(self, model: str) -> str:
        """The one answer for a model the service will not load, whether or not anything
        is at the path it names (so the answer tells nothing of the machine's files)."""
        return (f"{model!r} is not a model this service loads: name the bundled model "
                f"({DEFAULT_MODEL}), one in its Hugging Face cache, 'openai:<model>', or a "
                f"directory inside {self._model_dir} (AESOP_EMBEDDING_MODEL_DIR)")

    def _get(self, model: str) -> Embedder:
        key = pool_key(model)
        with self._lock:
            if self._closed:
                raise RuntimeError("the embedder pool is closed")
            slot = self._slots.setdefault(key, _Slot())
            self._slots.move_to_end(key)
        with slot.lock:
            if slot.embedder is None:
                slot.embedder = self._loader(model)
            embedder = slot.embedder
        self._evict()
        return embedder

    def _check_directory(self, model: str) -> None:
        if self._model_dir is None or model.startswith(OPENAI_PREFIX):
            return
        onnx = split_onnx(model)
        path = Path(model if onnx is None else onnx[0]).expanduser()
        if (is_dir(path) or path.is_absolute()) and \
                not path.resolve().is_relative_to(self._model_dir):
            raise ModelNotFound(self._refusal(model))

    def _evict(self) -> None:
        with self._lock:
            loaded = [key for key, slot in self._slots.items() if slot.embedder is not None]
            for key in loaded[:max(0, len(loaded) - self._max_loaded)]:
                del self._slots[key]  # a caller that holds it keeps using it

    def loaded(self) -> list[str]:
        """Names of the embedders loaded so far."""
        with self._lock:
            slots = list(self._slots.values())
        return [s.embedder.name for s in slots if s.embedder is not None]

    def close(self) -> None:
        """Closes every embedder (HTTP clients let go of their connections); idempotent."""
        with self._lock:
            self._closed = True
            slots, self._slots = list(self._slots.values()), OrderedDict()
        for slot in slots:
            with slot.lock:
                embedder, slot.embedder = slot.embedder, None
            if embedder is not None:
                embedder.close()


__all__ = ["EmbedderPool", "load_embedder"]
