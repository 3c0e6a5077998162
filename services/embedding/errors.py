"""The vector-cache service's exceptions; mapped to HTTP statuses only in ``api.py``.

DetectorError
 +-- InvalidInput      bad request content; ``field`` names it (e.g. "items[3].text")
 +-- NotFound          unknown cache, experience or job
 +-- Conflict          the request contradicts stored state (duplicate id, model change)
 +-- NotCalibrated     a threshold is needed and the cache has none
 +-- Busy              too much work is already waiting; ``field`` names the request part
"""

from __future__ import annotations


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
