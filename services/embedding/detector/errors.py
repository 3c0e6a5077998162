"""The vector-cache service's exceptions; mapped to HTTP statuses only in ``api.py``.

DetectorError
 +-- InvalidInput      bad request content; ``field`` names it (e.g. "items[3].text")
 +-- NotFound          unknown cache, experience or job
 +-- Conflict          the request contradicts stored state (duplicate id, model change)
 +-- NotCalibrated     a threshold is needed and the cache has none
 +-- Busy              too much work is already waiting; ``field`` names the request part

StorageError           a write that did not happen (rolled back), or a store that cannot be used
 +-- StorageFull       the disk (or the database's size limit) is full
 +-- StorageCorrupt    a file that cannot be trusted, left as it is
 +-- Behind            another replica changed the cache first (a shared store)
"""

from __future__ import annotations

from pathlib import Path


class DetectorError(Exception):
    code = "error"

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field


class InvalidInput(DetectorError):
    code = "invalid"


class NotFound(DetectorError):
    code = "not_found"


class Conflict(DetectorError):
    code = "conflict"


class NotCalibrated(DetectorError):
    code = "not_calibrated"


class Busy(DetectorError):
    code = "busy"


class StorageError(Exception):
    """A write that did not happen (rolled back), a database out of reach, or a lock held
    by another process."""


class StorageFull(StorageError):
    """The disk (or the database's size limit) is full; the write was rolled back."""


class StorageCorrupt(StorageError):
    """A file that cannot be trusted; it is left as it is for inspection."""

    def __init__(self, path: Path, detail: str) -> None:
        super().__init__(f"{path}: {detail}")
        self.path = path


class Behind(StorageError):
    """A write planned on a version of the cache that another replica has moved past;
    nothing was written, the replica catches up and the caller may retry."""

    def __init__(self, cache: str, planned_on: int, stored: int) -> None:
        super().__init__(f"cache {cache!r} changed on another replica (version {stored}, "
                         f"this one had {planned_on}); nothing was written, retry")
        self.cache = cache
        self.stored = stored
