"""What the stores write and read, row by row (pure): the same tables in SQLite and PostgreSQL.

The SQLite store (:mod:`.store`) and the PostgreSQL one (:mod:`.pgstore`) keep the same
tables and differ only in their SQL.

JSON columns are text (``json.dumps`` of the values), vectors little-endian float32 bytes,
calibration scores float64 bytes.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict
from typing import Any

import numpy as np

from shared.messages import Detection

from ..detector.cache import (
    Add,
    CacheConfig,
    CachedExperience,
    CalibrationScores,
    Configure,
    Delete,
    Header,
    Op,
    SetCalibration,
)
from ..detector.calibration import Calibration
from ..detector.proposals import Proposal


def f4(blob: bytes) -> np.ndarray:
    return np.frombuffer(blob, dtype="<f4").astype(np.float32)


def f8(blob: bytes) -> np.ndarray:
    return np.frombuffer(blob, dtype="<f8").astype(np.float64)


def header_row(header: Header) -> tuple[str, int, int, str | None, bool]:
    """(config, version, next_label, calibration, stale) of the ``caches`` table."""
    cal = None if header.calibration is None else json.dumps(header.calibration.to_dict())
    return (json.dumps(asdict(header.config)), header.version, header.next_label, cal,
            header.stale)


def header_of(config: str, version: int, next_label: int, calibration: str | None,
              stale: Any) -> Header:
    cal = None if calibration is None else Calibration(**json.loads(calibration))
    return Header(CacheConfig(**json.loads(config)), int(version), int(next_label), cal,
                  bool(stale))


def experience_of(ident: str, text: str | None, metadata: str, detections: str) -> CachedExperience:
    return CachedExperience(ident, text, json.loads(metadata),
                      tuple(Detection(**d) for d in json.loads(detections)))


def experience_rows(name: str, op: Add) -> list[tuple[Any, ...]]:
    """``experiences`` rows: (cache, label, id, text, metadata, vector, version, detections)."""
    little = np.ascontiguousarray(op.vectors, dtype="<f4")
    return [(name, label, e.id, e.text, json.dumps(dict(e.metadata)), row.tobytes(),
             op.version, json.dumps([d.model_dump(exclude_none=True) for d in e.detections]))
            for label, e, row in zip(op.labels, op.experiences, little, strict=True)]


def phrase_rows(op: Add) -> list[tuple[str, bytes]]:
    """(phrase, vector) of the detection phrases ``op`` brings."""
    return [(phrase, np.ascontiguousarray(v, dtype="<f4").tobytes())
            for phrase, v in op.detection_vectors.items()]


def change_of(op: Op) -> tuple[str, dict[str, Any]]:
    """The change log's (op, detail) of ``op``."""
    if isinstance(op, Add):
        detail: dict[str, Any] = {"count": len(op.labels)}
        if op.labels:
            detail |= {"first_label": op.labels[0], "last_label": op.labels[-1]}
        return "add", detail
    if isinstance(op, Delete):
        return "delete", {"id": op.id, "label": op.label}
    if isinstance(op, SetCalibration):
        return "calibrate", op.calibration.to_dict()
    return "configure", {"k": op.k, "score": op.score, "proposals": op.proposals}


def score_blobs(scores: CalibrationScores) -> tuple[bytes, bytes, bytes | None]:
    """(observation, detection, pair) of the ``calibration_scores`` table."""
    observation, detection, pair = (
        None if x is None else np.ascontiguousarray(x, dtype="<f8").tobytes()
        for x in (scores.observation, scores.detection, scores.pair))
    assert observation is not None and detection is not None
    return observation, detection, pair


def scores_of(row: Sequence[bytes | None] | None) -> CalibrationScores | None:
    if row is None:
        return None
    observation, detection, pair = row
    assert observation is not None and detection is not None
    return CalibrationScores(f8(observation), f8(detection), None if pair is None else f8(pair))


def proposal_row(name: str, proposal: Proposal) -> tuple[Any, ...]:
    """(cache, id, state, count, first_at, last_at, decided_at, detail) of ``proposals``."""
    return (name, proposal.id, proposal.state, proposal.count, proposal.first_at,
            proposal.last_at, proposal.decided_at, json.dumps(proposal.detail()))


def proposal_of(row: Sequence[Any]) -> Proposal:
    """A proposal from (id, state, count, first_at, last_at, decided_at, detail)."""
    ident, state, count, first, last, decided, detail = row
    return Proposal.stored(ident, state, int(count), first, last, decided, json.loads(detail))


def delete_op(detail: dict[str, Any], version: int) -> Delete:
    return Delete(detail["id"], int(detail["label"]), version)


def configure_op(detail: dict[str, Any], version: int) -> Configure:
    return Configure(int(detail["k"]), detail["score"], version, detail["proposals"])
