"""FAISS vector index with stable int64 labels: exact inner product, optional HNSW.

Vectors are L2-normalised float32 rows, so inner product is cosine similarity.
The exact index (``IndexFlatIP`` under ``IndexIDMap2``) is the source of truth
and holds the only copy of the vectors; an HNSW graph, when asked for, is an
acceleration structure derived from it: extended on add, rebuilt lazily after
a delete (HNSW cannot remove). Not thread-safe: the cache serialises writers
and lets readers in concurrently around it.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Literal

import faiss
import numpy as np
import torch

IndexKind = Literal["flat", "hnsw"]
# HNSW candidates per search: recall@5 0.966 at 1M vectors (64: 0.909) for 0.41 ms a query
# (aesop bench detector --only search, docs/benchmarks.md, search and restart)
EF_SEARCH = 128
FEW_QUERIES = 16  # searches of at most this many queries run on ``query_threads`` threads


@contextmanager
def omp_threads(n: int | None) -> Iterator[None]:
    """OpenMP threads for FAISS calls in this block, then restored. The setting is per
    calling thread (torch, which shares the OpenMP runtime, keeps its own elsewhere)."""
    if n is None:
        yield
        return
    before = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(n)
    try:
        yield
    finally:
        faiss.omp_set_num_threads(before)


class VectorIndex:
    """Labels -> unit vectors of dimension ``dim``, searched by inner product."""

    def __init__(
        self, dim: int, kind: IndexKind = "flat", *, hnsw_m: int = 32,
        ef_search: int = EF_SEARCH,
        ef_construction: int = 40, query_threads: int | None = 1,
    ) -> None:
        """``query_threads``: OpenMP threads for a search of at most FEW_QUERIES queries
        (None: FAISS's default). One thread is faster per query here: spreading one
        query over busy cores costs more than it gains (``aesop bench detector``)."""
        if dim < 1:
            raise ValueError("dim must be positive")
        self.dim = dim
        self.kind: IndexKind = kind
        self.hnsw_m = hnsw_m
        self.ef_search = ef_search
        self.ef_construction = ef_construction
        self.query_threads = query_threads
        self._flat = faiss.IndexFlatIP(dim)
        self._index = faiss.IndexIDMap2(self._flat)
        self._hnsw: faiss.IndexHNSWFlat | None = None
        self._hnsw_dirty = kind == "hnsw"

    def __len__(self) -> int:
        return int(self._index.ntotal)

    def set_ef_search(self, ef_search: int) -> None:
        """The HNSW candidate list of a search (more: better recall, slower queries)."""
        if ef_search < 1:
            raise ValueError("ef_search must be positive")
        self.ef_search = ef_search
        if self._hnsw is not None:
            self._hnsw.hnsw.efSearch = ef_search

    @property
    def graph_ready(self) -> bool:
        """An HNSW graph is built and current (a search will not rebuild it)."""
        return self._hnsw is not None and not self._hnsw_dirty

    def write(self, vectors: Path, graph: Path) -> bool:
        """Write the labelled vectors to ``vectors`` and, when it is current, the HNSW
        graph to ``graph``; returns whether the graph was written. Raises OSError or
        RuntimeError (FAISS's failed write, e.g. a full disk)."""
        faiss.write_index(self._index, str(vectors))
        if self._hnsw is not None and not self._hnsw_dirty:
            faiss.write_index(self._hnsw, str(graph))
            return True
        return False

    @classmethod
    def read(cls, dim: int, kind: IndexKind, vectors: Path, graph: Path | None = None
             ) -> VectorIndex:
        """An index written by :meth:`write`; ``graph`` (optional) must have been written
        with it. Raises RuntimeError (FAISS) or ValueError for a file that does not fit."""
        index = cls(dim, kind)
        idmap = faiss.read_index(str(vectors))
        if not isinstance(idmap, faiss.IndexIDMap2) or idmap.d != dim:
            raise ValueError(f"{vectors}: not a labelled index of dimension {dim}")
        flat = faiss.downcast_index(idmap.index)
        if not isinstance(flat, faiss.IndexFlatIP):
            raise ValueError(f"{vectors}: not an exact inner-product index")
        index._index, index._flat = idmap, flat
        if kind == "hnsw" and graph is not None:
            hnsw = faiss.read_index(str(graph))
            if not isinstance(hnsw, faiss.IndexHNSWFlat) or hnsw.ntotal != idmap.ntotal:
                raise ValueError(f"{graph}: not an HNSW graph over {idmap.ntotal} vectors")
            hnsw.hnsw.efSearch = index.ef_search
            index._hnsw, index._hnsw_dirty = hnsw, False
        return index

    def labels(self) -> np.ndarray:
        """(n,) int64 labels in storage order: a read-only view, valid until the next
        add or remove (copy it to keep it)."""
        n = len(self)
        if n == 0:
            return np.empty(0, dtype=np.int64)
        view = faiss.rev_swig_ptr(self._index.id_map.data(), n)
        view.flags.writeable = False
        return view

    def vectors(self) -> np.ndarray:
        """(n, dim) float32 view of the stored vectors, in storage order (do not mutate)."""
        n = len(self)
        if n == 0:
            return np.empty((0, self.dim), dtype=np.float32)
        return faiss.rev_swig_ptr(self._flat.get_xb(), n * self.dim).reshape(n, self.dim)

    def add(self, vectors: np.ndarray, labels: np.ndarray) -> None:
        vectors = np.ascontiguousarray(vectors, dtype=np.float32)
        labels = np.ascontiguousarray(labels, dtype=np.int64)
        if vectors.ndim != 2 or vectors.shape[1] != self.dim or len(vectors) != len(labels):
            raise ValueError(f"expected ({len(labels)}, {self.dim}) vectors, got {vectors.shape}")
        self._index.add_with_ids(vectors, labels)
        if self._hnsw is not None and not self._hnsw_dirty:
            self._hnsw.add(vectors)

    def remove(self, labels: np.ndarray) -> int:
        ids = np.ascontiguousarray(labels, dtype=np.int64)
        # faiss's Python wrapper takes an id array; its SWIG stub only knows IDSelector
        removed = int(self._index.remove_ids(ids))  # type: ignore[arg-type]
        if removed and self.kind == "hnsw":
            self._hnsw_dirty = True
        return removed

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-k by cosine similarity: ((nq, k) similarities descending, (nq, k) labels).

        Uses the HNSW graph when the index is approximate, else exact search.
        """
        queries = np.ascontiguousarray(queries, dtype=np.float32)
        k = min(k, len(self))
        if self.kind == "hnsw" and len(self) > 0:
            graph = self._graph()
            with self._threads(len(queries)):
                sims, rows = graph.search(queries, k)
            labels = self.labels()
            return sims, np.where(rows >= 0, labels[np.maximum(rows, 0)], -1)
        return self.search_exact(queries, k)

    def search_exact(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        queries = np.ascontiguousarray(queries, dtype=np.float32)
        with self._threads(len(queries)):
            return self._index.search(queries, min(k, len(self)))

    def _threads(self, n_queries: int) -> AbstractContextManager[None]:
        return omp_threads(self.query_threads if n_queries <= FEW_QUERIES else None)

    def self_search(self, k: int, *, block: int = 2048) -> tuple[np.ndarray, np.ndarray]:
        """Exact top-k neighbours of every member among all members (itself included).

        Blocked matrix product plus top-k selection; about twice as fast as FAISS's
        batched search here (see ``aesop bench detector``). Returns ((n, k) sims,
        (n, k) labels) with k clipped to n.
        """
        x = torch.from_numpy(np.array(self.vectors()))
        labels = self.labels()
        k = min(k, len(x))
        sims = np.empty((len(x), k), dtype=np.float32)
        rows = np.empty((len(x), k), dtype=np.int64)
        with torch.inference_mode():
            for start in range(0, len(x), block):
                values, idx = torch.topk(x[start : start + block] @ x.T, k, dim=1)
                sims[start : start + block] = values.numpy()
                rows[start : start + block] = idx.numpy()
        return sims, labels[rows]

    def _graph(self) -> faiss.IndexHNSWFlat:
        if self._hnsw is None or self._hnsw_dirty:
            graph = faiss.IndexHNSWFlat(self.dim, self.hnsw_m, faiss.METRIC_INNER_PRODUCT)
            graph.hnsw.efSearch = self.ef_search
            graph.hnsw.efConstruction = self.ef_construction
            if len(self):
                graph.add(np.ascontiguousarray(self.vectors()))
            self._hnsw, self._hnsw_dirty = graph, False
        return self._hnsw
