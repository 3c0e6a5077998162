"""A replica's index files: each cache's versioned FAISS index beside its store, saved safely.

Each cache's FAISS index as of a version is under
``<data_dir>/indexes/<cache>/v<version>.faiss`` (and its HNSW graph, once built,
``v<version>.hnsw``).

The index is derived data: the database (SQLite or PostgreSQL, :mod:`.store`,
:mod:`.pgstore`) holds every vector. A file is written to a temporary name, fsync'd and
renamed; a failed save loses nothing. On open, a file at the cache's version is loaded as
it is (an HNSW graph over a million vectors is not rebuilt); an older one is loaded and
caught up from the database; with none, or one that does not fit, the index is built from
the stored vectors.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Self

from ..detector.cache import Cache, Header
from ..detector.errors import StorageError
from ..detector.index import VectorIndex

log = logging.getLogger(__name__)

INDEX_DIR = "indexes"


class IndexFiles:
    """The index files under ``root``; ``fsync=False`` skips their fsync."""

    def __init__(self, root: Path, *, fsync: bool = True) -> None:
        self.root = Path(root)
        self._fsync = fsync

    def restore(self, header: Header, labels: set[int],
                catch_up: Callable[[VectorIndex, int], None],
                build: Callable[[VectorIndex], None]) -> VectorIndex:
        """The index of a cache stored at ``header``, holding exactly ``labels``: from the
        newest usable file, ``catch_up(index, its version)`` when it is older, or
        ``build(empty index)`` from the stored vectors."""
        config = header.config
        for version, vectors, graph in self._files(config.name):
            if version > header.version:
                continue
            try:
                index = VectorIndex.read(config.dim, config.index, vectors,
                                         graph if graph.exists() else None)
                if version < header.version:
                    catch_up(index, version)
                if set(index.labels().tolist()) != labels:
                    raise ValueError("its labels differ from the stored experiences")
            except (RuntimeError, ValueError) as exc:
                log.warning("cache %s: not using %s (%s)", config.name, vectors, exc)
                continue
            log.info("cache %s: index loaded from %s%s", config.name, vectors.name,
                     f", caught up from version {version}" if version < header.version else "")
            return index
        index = VectorIndex(config.dim, config.index)
        build(index)
        return index

    def save(self, cache: Cache) -> Path:
        """Write ``cache``'s index as of its version; older files are removed after.
        The caller keeps the cache from changing meanwhile. Raises StorageError."""
        name, version = cache.name, cache.version
        directory = self.root / INDEX_DIR / name
        vectors, graph = _paths(directory, version)
        tmp_vectors, tmp_graph = (p.with_name(p.name + ".tmp") for p in (vectors, graph))
        try:
            directory.mkdir(mode=0o700, parents=True, exist_ok=True)
            for folder in (directory.parent, directory):
                folder.chmod(0o700)
            with_graph = cache.index.write(tmp_vectors, tmp_graph)
            for tmp, final in [(tmp_vectors, vectors)] + ([(tmp_graph, graph)] * with_graph):
                tmp.chmod(0o600)
                self._sync(tmp)
                os.replace(tmp, final)
            self._sync(directory, directory=True)
        except (OSError, RuntimeError) as exc:
            for tmp in (tmp_vectors, tmp_graph):
                with contextlib.suppress(OSError):
                    tmp.unlink(missing_ok=True)
            raise StorageError(f"{vectors}: index not saved ({exc}); the database has it all"
                               ) from exc
        for old, old_vectors, old_graph in self._files(name):
            if old != version:
                old_vectors.unlink(missing_ok=True)
                old_graph.unlink(missing_ok=True)
        return vectors

    def saved(self, name: str) -> tuple[int, bool] | None:
        """(version, has the HNSW graph) of the newest index file of ``name``, if any."""
        files = self._files(name)
        return None if not files else (files[0][0], files[0][2].exists())

    def _files(self, name: str) -> list[tuple[int, Path, Path]]:
        """(version, vectors file, graph file) of the saved indexes, newest first."""
        directory = self.root / INDEX_DIR / name
        if not directory.is_dir():
            return []
        found = []
        for path in directory.glob("v*.faiss"):
            if path.stem[1:].isdigit():
                found.append((int(path.stem[1:]), *_paths(directory, int(path.stem[1:]))))
        for leftover in directory.glob("*.tmp"):
            leftover.unlink(missing_ok=True)
        return sorted(found, reverse=True)

    def _sync(self, path: Path, *, directory: bool = False) -> None:
        if self._fsync:
            fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
            try:
                os.fsync(fd)
            finally:
                os.close(fd)


def _paths(directory: Path, version: int) -> tuple[Path, Path]:
    return directory / f"v{version}.faiss", directory / f"v{version}.hnsw"


class WithIndexFiles:
    """What both stores share: their replica's index files, and closing by ``with``."""

    indexes: IndexFiles

    def save_index(self, cache: Cache) -> Path:
        """Write ``cache``'s index file. Raises StorageError."""
        return self.indexes.save(cache)

    def saved_index(self, name: str) -> tuple[int, bool] | None:
        return self.indexes.saved(name)

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
