"""One log format per process, for its own lines and uvicorn's: text, or JSON lines.

Every process of the stack logs as text for a terminal, or as JSON lines for a log collector
(``AESOP_LOG_FORMAT=json``).

A JSON line holds ``time`` (UTC, ISO 8601 to the millisecond), ``level``, ``logger``,
``message``, ``pid`` and, for a logged exception, ``exception`` (its traceback)."""

from __future__ import annotations

import json
import logging
import os
import sys
from datetime import UTC, datetime
from typing import Literal, get_args

LogFormat = Literal["text", "json"]
TEXT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
VARIABLE = "AESOP_LOG_FORMAT"


class JsonLines(logging.Formatter):
    """One JSON object per record, on one line."""

    def format(self, record: logging.LogRecord) -> str:
        line = {"time": datetime.fromtimestamp(record.created, UTC).isoformat(
                    timespec="milliseconds").replace("+00:00", "Z"),
                "level": record.levelname, "logger": record.name,
                "message": record.getMessage(), "pid": record.process}
        if record.exc_info:
            line["exception"] = self.formatException(record.exc_info)
        elif record.exc_text:
            line["exception"] = record.exc_text
        return json.dumps(line, ensure_ascii=False, default=str)


def log_format(environ: dict[str, str] | os._Environ[str] | None = None) -> LogFormat:
    """The format ``AESOP_LOG_FORMAT`` names (text when unset); a clear error otherwise."""
    value = (os.environ if environ is None else environ).get(VARIABLE, "text").strip().lower()
    if value not in get_args(LogFormat):
        raise ValueError(f"{VARIABLE}: expected text or json, got {value!r}")
    return value  # type: ignore[return-value]


def configure(level: int | str = logging.INFO, fmt: LogFormat = "text") -> None:
    """The root logger writes ``fmt`` lines to stderr from ``level`` on (replacing any
    handler it had): every library's logger, uvicorn's included, propagates to it."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonLines() if fmt == "json" else logging.Formatter(TEXT))
    if isinstance(level, str):
        level = level.upper()
    logging.basicConfig(level=level, handlers=[handler], force=True)
