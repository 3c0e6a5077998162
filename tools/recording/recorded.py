"""What a recording holds, decoded: its observations (within a time window) and the
verdicts the detector gave them when it was recorded. The readers of ``aesop cache
import`` and ``aesop detector eval --recording``; no Zenoh, no HTTP.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from pydantic import ValidationError

from shared.messages import AnomalyVerdict, Observation

from .mcapfile import Recorded, read_messages

MAGIC = b"\x89MCAP0\r\n"


class RecordingError(ValueError):
    """A file that is not a recording, or a window that selects nothing sensible."""


def check_recording(path: Path) -> None:
    """Raise :class:`RecordingError` unless ``path`` is a readable MCAP file."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MAGIC))
    except OSError as exc:
        raise RecordingError(f"cannot read {path}: {exc.strerror}") from None
    if head != MAGIC:
        raise RecordingError(f"{path} is not an MCAP file")


def parse_when(text: str, start_ns: int) -> int:
    """A point of a recording, as ns since the epoch: seconds from ``start_ns`` (``12.5``;
    :func:`observations` gives its first observation's time) or a time
    (``2026-11-23T10:15:00``, UTC unless it names a zone)."""
    try:
        return start_ns + round(float(text.removesuffix("s")) * 1e9)
    except ValueError:
        pass
    try:
        when = datetime.fromisoformat(text)
    except ValueError:
        raise RecordingError(f"{text!r} is neither seconds from the recording's first "
                             "observation nor an ISO 8601 time") from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return round(when.timestamp() * 1e9)


@dataclass(frozen=True)
class RecordedObservation:
    observation: Observation
    log_time_ns: int
    key: str
    source: str  # the recording's file name


def observations(path: Path, *, robot: str | None = None, since: str | None = None,
                 until: str | None = None) -> Iterator[RecordedObservation]:
    """The observations of ``robot`` (every robot by default) that arrived in the
    window [since, until] (see :func:`parse_when`), in the order recorded, in one pass
    over the file. Seconds count from the first of those observations, when the camera
    came on, not from the recording's first message: a recorder runs before the flight
    does (``aesop demo`` starts it while it sets the flight up, seconds of states and
    plans before the first observation), so ``--until 3`` is the first 3 s the camera
    saw. A message that does not decode (recorded by another version) is skipped."""
    low = high = None
    first = True
    for record in read_messages(path):
        if not _is_kind(record, "observation", robot):
            continue
        if first:
            first = False
            low = parse_when(since, record.log_time_ns) if since is not None else None
            high = parse_when(until, record.log_time_ns) if until is not None else None
            if low is not None and high is not None and high < low:
                raise RecordingError(f"--until ({until}) is before --since ({since})")
        if (low is not None and record.log_time_ns < low) or (
                high is not None and record.log_time_ns > high):
            continue
        try:
            message = Observation.decode(record.data)
        except ValidationError:
            continue
        yield RecordedObservation(message, record.log_time_ns, record.key, path.name)


def verdicts(path: Path, robot: str | None = None) -> dict[tuple[str, int], AnomalyVerdict]:
    """The recorded verdicts by (robot, observation seq): the last one of each."""
    out: dict[tuple[str, int], AnomalyVerdict] = {}
    for record in _of_kind(path, "anomaly", robot):
        try:
            verdict = AnomalyVerdict.decode(record.data)
        except ValidationError:
            continue
        out[(verdict.robot, verdict.seq)] = verdict
    return out


def _of_kind(path: Path, kind: str, robot: str | None) -> Iterator[Recorded]:
    return (record for record in read_messages(path) if _is_kind(record, kind, robot))


def _is_kind(record: Recorded, kind: str, robot: str | None) -> bool:
    parts = record.key.split("/", 2)
    return len(parts) == 3 and parts[2] == kind and robot in (None, parts[1])
