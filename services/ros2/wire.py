"""rmw_zenoh's wire format, as ros2/rmw_zenoh writes it (pure).

From its design document (``docs/design.md``) and its sources
(``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp``, ``attachment_helpers.cpp``), for
Jazzy and later (rmw_zenoh_cpp 0.2.4+):

* **Data key** of a topic: ``<domain_id>/<fully qualified name without its leading
  slash>/<type as pkg::msg::dds_::Name_>/<RIHS01 type hash>``; the name keeps its inner
  slashes (``0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...``).
* **Payload**: the message in CDR with its 4-byte encapsulation header (``rosbags``
  writes and reads it, :mod:`.convert`).
* **Attachment** of every sample, 33 bytes positional: the publisher's sequence number
  (int64 LE, from 1), its source timestamp (ns since the epoch, int64 LE), the GID's length
  (one byte, 16) and the publisher's 16-byte GID. A ROS subscriber drops a sample without
  one, and so does the bridge. Releases 0.2.0 to 0.2.3 (early Jazzy) wrote the same three
  fields as a keyed zenoh-ext serialisation (each field's name as a length-prefixed string
  before it, 77 bytes); :func:`parse_attachment` reads both.
* **Liveliness tokens** (the ROS graph: ``ros2 node list``, ``ros2 topic list``):
  ``@ros2_lv/<domain>/<session zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/
  <node name>[/<topic>/<type>/<type hash>/<qos>]``, kinds ``NN`` (node), ``MP``
  (publisher), ``MS`` (subscriber); names *mangled*: every ``/`` becomes ``%`` and an
  empty name is ``%``. The QoS is written as its differences from rmw_zenoh's default
  profile (``detail/qos.cpp``: reliable, volatile, keep last 42, infinite deadline and
  lifespan, automatic liveliness), so a reliable volatile keep-last-10 endpoint's is
  ``::,10:,:,:,,`` and one with depth 7 ``::,7:,:,:,,``.

Humble's rmw_zenoh (0.1.x) has no type hashes (``TypeHashNotSupported`` in the key): it
is not supported here.
"""

from __future__ import annotations

import copy
import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import xxhash

LIVELINESS = "@ros2_lv"
GID_BYTES = 16
# rmw_zenoh's DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5 (jazzy 0.2.10), the keys where it
# differs from Zenoh's defaults: a session file given to its nodes (ZENOH_SESSION_CONFIG_URI)
# replaces that file whole, so one that leaves these out turns timestamping off (no
# BEST_EFFORT + TRANSIENT_LOCAL publisher can then be made), the 10-minute query timeout
# and the 60 s lease with it; :func:`session_config` keeps them
SESSION_DEFAULTS: dict[str, Any] = {
    "mode": "peer",
    "connect": {"endpoints": ["tcp/localhost:7447"]},
    "listen": {"endpoints": ["tcp/localhost:0"]},
    "scouting": {
        "multicast": {"enabled": False,
                      "autoconnect_strategy": {"peer": {"to_router": "always",
                                                        "to_peer": "greater-zid"}}},
        "gossip": {"target": {"router": ["router", "peer"], "peer": ["router"]},
                   "autoconnect_strategy": {"peer": {"to_router": "always",
                                                     "to_peer": "greater-zid"}}}},
    "timestamping": {"enabled": {"router": True, "peer": True, "client": True}},
    "queries_default_timeout": 600000,
    "transport": {
        "unicast": {"open_timeout": 60000, "accept_timeout": 60000, "accept_pending": 10000,
                    "max_sessions": 10000},
        "link": {"tx": {"lease": 60000, "keep_alive": 2,
                        "queue": {"congestion_control": {
                            "block": {"wait_before_close": 60000000}}}}},
        "shared_memory": {"enabled": False}},
    "adminspace": {"enabled": True, "permissions": {"read": True, "write": False}},
}
ATTACHMENT_BYTES = 8 + 8 + 1 + GID_BYTES  # 33
MAX_ATTACHMENT_BYTES = 128  # past either form (33, 77 bytes): refused before it is copied
_POSITIONAL = struct.Struct("<qqB")
# 0.2.0-0.2.3: zenoh-ext serialised (name, value) pairs; the names as they wrote them
_KEYED_NAMES = (b"sequence_number", b"source_timestamp", b"source_gid")

_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv|action)/([A-Za-z][A-Za-z0-9_]*)$")
_TOPIC = re.compile(r"^/?[A-Za-z_~{][A-Za-z0-9_/{}~]*$")
_HASH = re.compile(r"^RIHS01_[0-9a-f]{64}$")

# rmw's QoS enums (rmw/types.h)
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST = 1
ZENOH_DEPTH = 42  # rmw_zenoh's default depth (what it writes as nothing)
DEFAULT_DEPTH = 10  # the bridge's endpoints' (rclcpp's usual)


class WireError(ValueError):
    """A name, type or attachment that rmw_zenoh would not write."""


def dds_type_name(ros_type: str) -> str:
    """``nav_msgs/msg/Odometry`` -> ``nav_msgs::msg::dds_::Odometry_``."""
    match = _TYPE.match(ros_type)
    if match is None:
        raise WireError(f"not a ROS 2 type name (pkg/msg/Name): {ros_type!r}")
    package, kind, name = match.groups()
    return f"{package}::{kind}::dds_::{name}_"


def fully_qualified(topic: str, namespace: str = "/") -> str:
    """A topic's fully qualified name: absolute names as they are, relative ones under
    ``namespace`` (``chatter`` in ``/robot1`` -> ``/robot1/chatter``)."""
    if not _TOPIC.match(topic) or "//" in topic or (len(topic) > 1 and topic.endswith("/")):
        raise WireError(f"not a ROS 2 topic name: {topic!r}")
    if topic.startswith("/"):
        return topic
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{topic}"


def check_hash(type_hash: str) -> str:
    if not _HASH.match(type_hash):
        raise WireError(f"not a RIHS01 type hash: {type_hash!r}")
    return type_hash


def data_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The Zenoh key rmw_zenoh puts a topic's samples on (``topic``: fully qualified)."""
    return (f"{domain_id}/{fully_qualified(topic)[1:]}/{dds_type_name(ros_type)}/"
            f"{check_hash(type_hash)}")


def topic_keys(domain_id: int, topic: str) -> str:
    """Every data key of ``topic``, whatever its type and hash (``<d>/<topic>/*/*``)."""
    return f"{domain_id}/{fully_qualified(topic)[1:]}/*/*"


def mangle(name: str) -> str:
    """A name in a liveliness token: ``/`` -> ``%``, empty -> ``%``."""
    return name.replace("/", "%") if name else "%"


def qos_keyexpr(*, reliability: int = RELIABLE, durability: int = VOLATILE,
                history: int = KEEP_LAST, depth: int = DEFAULT_DEPTH) -> str:
    """A QoS profile as rmw_zenoh writes it in a token: each field only where it differs
    from its default profile (deadline, lifespan and liveliness: the defaults)."""

    def differs(value: int, default: int) -> str:
        return "" if value == default else str(value)

    return (f"{differs(reliability, RELIABLE)}:{differs(durability, VOLATILE)}:"
            f"{differs(history, KEEP_LAST)},{differs(depth, ZENOH_DEPTH)}:,:,:,,")


@dataclass(frozen=True)
class Node:
    """Who the bridge is in the ROS graph."""

    domain_id: int
    zid: str  # the Zenoh session id, as rmw_zenoh writes it (32 hex digits)
    name: str
    namespace: str = "/"  # "/" or "/robot1"
    enclave: str = ""
    node_id: int = 0

    def token(self) -> str:
        """The node's liveliness token (``NN``)."""
        return f"{self._prefix(self.node_id)}/NN/{self._names()}"

    def entity_token(self, entity_id: int, kind: str, topic: str, ros_type: str,
                     type_hash: str, qos: str) -> str:
        """A publisher's (``MP``) or subscriber's (``MS``) token."""
        if kind not in ("MP", "MS"):
            raise WireError(f"entity kind {kind!r}: MP or MS")
        return (f"{self._prefix(entity_id)}/{kind}/{self._names()}/"
                f"{mangle(fully_qualified(topic, self.namespace))}/{dds_type_name(ros_type)}/"
                f"{check_hash(type_hash)}/{qos}")

    def _prefix(self, entity_id: int) -> str:
        return f"{LIVELINESS}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}"

    def _names(self) -> str:
        namespace = "" if self.namespace.strip("/") == "" else self.namespace
        return f"{mangle(self.enclave)}/{mangle(namespace)}/{self.name}"


def session_config(overrides: Mapping[str, Any]) -> dict[str, Any]:
    """rmw_zenoh's default session config with ``overrides`` merged in, key by key (a
    mapping into a mapping, anything else replaced): what a session file for a robot's
    nodes must hold."""
    return _merged(SESSION_DEFAULTS, overrides)


def _merged(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(dict(base))
    for key, value in over.items():
        old = out.get(key)
        out[key] = (_merged(old, value) if isinstance(old, Mapping) and isinstance(value, Mapping)
                    else copy.deepcopy(value))
    return out


def gid(token: str) -> bytes:
    """An entity's 16-byte GID as rmw_zenoh computes it (``Entity::Entity`` in its
    liveliness_utils.cpp, every release 0.2.0-0.12.0): XXH3-128 (seed 0) of the entity's
    liveliness token, the low 64 bits then the high 64 bits, each little-endian. A robot's
    ``ros2 topic info -v`` rebuilds the token it sees and shows this same hash."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_BYTES, "little")


@dataclass(frozen=True)
class Attachment:
    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        """The 33-byte positional form (Jazzy, rmw_zenoh_cpp 0.2.4 and later)."""
        if len(self.gid) != GID_BYTES:
            raise WireError(f"a GID has {GID_BYTES} bytes, not {len(self.gid)}")
        return _POSITIONAL.pack(self.sequence_number, self.source_timestamp_ns,
                                GID_BYTES) + self.gid


def parse_attachment(raw: bytes | None) -> Attachment:
    """A sample's attachment in either form rmw_zenoh has written (:class:`WireError`:
    none, or not one of them)."""
    if raw is None or len(raw) == 0:
        raise WireError("no attachment")
    if len(raw) == ATTACHMENT_BYTES and raw[16] == GID_BYTES:
        seq, stamp, _ = _POSITIONAL.unpack_from(raw)
        return Attachment(seq, stamp, bytes(raw[17:]))
    return _parse_keyed(bytes(raw))


def _parse_keyed(raw: bytes) -> Attachment:
    """The 0.2.0-0.2.3 form: ``<len>name int64``, ``<len>name int64``, ``<len>name
    <len>gid`` (lengths as one-byte LEB128 varints)."""
    values: list[int | bytes] = []
    at = 0
    try:
        for i, name in enumerate(_KEYED_NAMES):
            if raw[at] != len(name) or raw[at + 1:at + 1 + len(name)] != name:
                raise WireError("attachment: neither rmw_zenoh form")
            at += 1 + len(name)
            if i < 2:
                values.append(struct.unpack_from("<q", raw, at)[0])
                at += 8
            else:
                size = raw[at]
                values.append(raw[at + 1:at + 1 + size])
                at += 1 + size
    except (IndexError, struct.error):
        raise WireError("attachment: truncated") from None
    seq, stamp, source = values
    if at != len(raw) or not isinstance(source, bytes) or len(source) != GID_BYTES:
        raise WireError("attachment: neither rmw_zenoh form")
    assert isinstance(seq, int) and isinstance(stamp, int)
    return Attachment(seq, stamp, source)

