"""The stack's messages as MCAP: a channel per Zenoh key, JSON messages, a JSON Schema per type.

Each type's schema is generated from its pydantic model, so Foxglove opens a file
and plots any field.

:class:`FlightWriter` is the file side (no Zenoh): ``add(key, payload, received_ns)``
registers a key's schema and channel the first time it is seen. The file is written in
chunks of ``chunk_size`` bytes, each handed to the OS once complete, so a recorder
killed with SIGKILL leaves a file readable up to its last completed chunk
(:func:`read_messages` reads such a file too); ``close`` writes the summary that makes
the file indexed.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.exceptions import McapError
from mcap.records import Channel, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from shared import topics
from shared.messages import (
    AnomalyVerdict,
    ControlState,
    Event,
    Message,
    Observation,
    PlanSnapshot,
    ReasonerDecision,
    ReasonerRequest,
    Regions,
    VehicleSetpoint,
    VehicleState,
)

# the last part(s) of a robot's key -> its message type (docs/architecture.md, section 3)
MODELS: dict[str, type[Message]] = {
    "observation": Observation,
    "anomaly": AnomalyVerdict,
    "state": ControlState,
    "plan": PlanSnapshot,
    "reasoner/request": ReasonerRequest,
    "reasoner/decision": ReasonerDecision,
    "event": Event,  # aesop/<robot>/event/<source>
    "regions": Regions,
    "vehicle/state": VehicleState,
    "vehicle/setpoint": VehicleSetpoint,
}
CHUNK_BYTES = 64 * 1024  # a SIGKILL loses at most this much of the newest messages


def check_topics(wanted: Sequence[str] | None) -> list[str]:
    """The topic names asked for (every one when None), or ValueError naming the ones
    that are not in :data:`MODELS`."""
    unknown = [t for t in wanted or () if t not in MODELS]
    if unknown:
        raise ValueError(f"unknown topic(s) {', '.join(unknown)}: choose from "
                         f"{', '.join(MODELS)}")
    return list(wanted or MODELS)


def topic_of(key: str) -> str | None:
    """The topic (a name in :data:`MODELS`) of a concrete robot key: ``state`` for
    ``aesop/robot0/state``, ``event`` for any source's ``aesop/robot0/event/control``;
    else None."""
    parts = key.split("/", 2)
    if len(parts) < 3 or parts[0] != topics.PREFIX or parts[1] == "health":
        return None
    name = parts[2]
    if name.startswith("event/"):  # one key per source
        name = "event"
    return name if name in MODELS else None


def model_of(key: str) -> type[Message] | None:
    """The message type of a concrete robot key (``aesop/robot0/state``), else None."""
    name = topic_of(key)
    return None if name is None else MODELS[name]


def key_expr(who: str, name: str) -> str:
    """What to subscribe for topic ``name`` of robot ``who`` (``*``: every robot)."""
    suffix = "event/*" if name == "event" else name
    return f"{topics.PREFIX}/{who}/{suffix}"


@dataclass(frozen=True)
class Recorded:
    """One message read back: its key, type name, JSON payload and receive time (ns)."""

    key: str
    schema: str
    data: bytes
    log_time_ns: int


class FlightWriter:
    """An MCAP file being written; see the module docstring."""

    def __init__(self, path: Path, *, chunk_size: int = CHUNK_BYTES) -> None:
        self.path = path
        self._file: BinaryIO = open(path, "wb")  # noqa: SIM115 (closed in close)
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="aesop-stack")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence = 0
        self.messages = 0
        self.bytes = 0

    def add(self, key: str, payload: bytes, received_ns: int, stamp_ns: int | None = None
            ) -> bool:
        """Write one message; False (and nothing written) for a key of no known type."""
        model = model_of(key)
        if model is None:
            return False
        channel = self._channels.get(key)
        if channel is None:
            channel = self._writer.register_channel(
                topic=key, message_encoding="json", schema_id=self._schema(model))
            self._channels[key] = channel
        self._sequence += 1
        self._writer.add_message(channel_id=channel, log_time=received_ns, data=payload,
                                 publish_time=stamp_ns if stamp_ns is not None else received_ns,
                                 sequence=self._sequence)
        self._file.flush()  # a chunk the writer completed goes to the OS now (else a no-op)
        self.messages += 1
        self.bytes += len(payload)
        return True

    def _schema(self, model: type[Message]) -> int:
        name = model.__name__
        if name not in self._schemas:
            schema = json.dumps(model.model_json_schema()).encode()
            self._schemas[name] = self._writer.register_schema(
                name=name, encoding="jsonschema", data=schema)
        return self._schemas[name]

    def close(self) -> None:
        """Finish the file: the last chunk, then the summary and its index."""
        try:
            self._writer.finish()
        finally:
            self._file.close()


def read_messages(path: Path) -> Iterator[Recorded]:
    """Every message of a file in the order written, as far as it can be read: a file
    whose recorder was killed ends after its last complete chunk."""
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, int]] = {}
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    channels[record.id] = (record.topic, record.schema_id)
                elif isinstance(record, McapMessage):
                    topic, schema_id = channels[record.channel_id]
                    yield Recorded(topic, schemas.get(schema_id, ""), record.data,
                                   record.log_time)
        except (McapError, EOFError, ValueError):
            return  # a torn tail: everything before it was read
