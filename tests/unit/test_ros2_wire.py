"""rmw_zenoh's wire format (services/ros2/wire.py) against the examples of its design
document, ros2/rmw_zenoh ``docs/design.md`` (rolling, the sections "Topic keys",
"Graph Cache" and "Publishers"), and its sources (``rmw_zenoh_cpp/src/detail/qos.cpp``,
``liveliness_utils.cpp``, ``attachment_helpers.cpp``)."""

from __future__ import annotations

import json
import struct

import pytest
import zenoh

from services.ros2 import convert, wire
from tools.stack.acl import ros2_session_config

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_the_data_key_is_the_design_documents():
    # design.md, "Topic keys", examples using demo_nodes_cpp
    assert wire.data_key(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert wire.data_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH) == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    adds = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
    assert wire.data_key(2, "/add_two_ints", "example_interfaces/srv/AddTwoInts", adds) == \
        f"2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{adds}"


def test_the_type_hash_is_the_one_ros_computes():
    # the hash in every std_msgs/msg/String example of design.md
    assert convert.type_hash("std_msgs/msg/String") == STRING_HASH


def test_node_and_entity_tokens_are_the_design_documents():
    # design.md, "Graph Cache", examples using demo_nodes_cpp (all on domain 2)
    zid = "aac3178e146ba6f1fc6e6a4085e77f21"
    listener = wire.Node(2, zid, "listener")
    assert listener.token() == f"@ros2_lv/2/{zid}/0/0/NN/%/%/listener"
    # the listener's subscription on chatter (rclcpp's QoS: reliable, volatile, keep last 10)
    assert listener.entity_token(10, "MS", "/chatter", "std_msgs/msg/String", STRING_HASH,
                                 wire.qos_keyexpr(depth=10)) == \
        f"@ros2_lv/2/{zid}/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/" \
        f"{STRING_HASH}/::,10:,:,:,,"
    # the talker's publisher on chatter (demo_nodes_cpp's talker: depth 7)
    talker = wire.Node(2, "8b20917502ee955ac4476e0266340d5c", "talker")
    assert talker.entity_token(10, "MP", "chatter", "std_msgs/msg/String", STRING_HASH,
                               wire.qos_keyexpr(depth=7)) == \
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/" \
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"


def test_names_are_mangled_and_namespaces_resolved():
    node = wire.Node(0, "z", "bridge", namespace="/robot1")
    assert node.token() == "@ros2_lv/0/z/0/0/NN/%/%robot1/bridge"
    assert "/%robot1%odom/" in node.entity_token(1, "MS", "odom", "nav_msgs/msg/Odometry",
                                                  STRING_HASH, wire.qos_keyexpr())
    assert wire.fully_qualified("odom", "/robot1") == "/robot1/odom"
    assert wire.fully_qualified("/odom", "/robot1") == "/odom"
    for bad in ("", "a//b", "/a/", "1abc", "/a b"):
        with pytest.raises(wire.WireError):
            wire.fully_qualified(bad)


def test_qos_is_written_as_its_differences_from_rmw_zenohs_defaults():
    assert wire.qos_keyexpr(depth=42) == "::,:,:,:,,"  # qos.cpp: keep last 42
    assert wire.qos_keyexpr(reliability=wire.BEST_EFFORT, durability=wire.TRANSIENT_LOCAL,
                            depth=1) == "2:1:,1:,:,:,,"


def test_the_attachment_is_33_bytes_positional():
    # design.md, "Publishers": sequence number int64 LE, timestamp ns int64 LE, the GID's
    # length (one byte, 16), the 16-byte GID
    gid = bytes(range(16))
    raw = wire.Attachment(7, 1_700_000_000_123_456_789, gid).encode()
    assert len(raw) == 33
    assert raw == struct.pack("<qqB", 7, 1_700_000_000_123_456_789, 16) + gid
    assert wire.parse_attachment(raw) == wire.Attachment(7, 1_700_000_000_123_456_789, gid)


def keyed_attachment(att: wire.Attachment) -> bytes:
    """What rmw_zenoh 0.2.0-0.2.3 wrote: zenoh-ext serialised (name, value) pairs, each
    name a length-prefixed string, the GID a length-prefixed byte string."""
    return (b"\x0fsequence_number" + struct.pack("<q", att.sequence_number)
            + b"\x10source_timestamp" + struct.pack("<q", att.source_timestamp_ns)
            + b"\x0asource_gid" + bytes([len(att.gid)]) + att.gid)


def test_the_older_keyed_attachment_is_read_too():
    att = wire.Attachment(3, 42, b"\xab" * 16)
    keyed = keyed_attachment(att)
    assert len(keyed) == 77
    assert keyed.startswith(b"\x0fsequence_number") and b"\x0asource_gid\x10" in keyed
    assert wire.parse_attachment(keyed) == att


@pytest.mark.parametrize("raw", [None, b"", b"\x00" * 32, b"\x00" * 34,
                                 keyed_attachment(wire.Attachment(1, 2, b"x" * 16))[:-1]])
def test_no_or_a_bad_attachment_is_refused(raw: bytes | None):
    with pytest.raises(wire.WireError):
        wire.parse_attachment(raw)


def test_type_names_and_hashes_are_checked():
    assert wire.dds_type_name("nav_msgs/msg/Odometry") == "nav_msgs::msg::dds_::Odometry_"
    with pytest.raises(wire.WireError):
        wire.dds_type_name("nav_msgs/Odometry")
    with pytest.raises(wire.WireError):
        wire.data_key(0, "/a", "std_msgs/msg/String", "TypeHashNotSupported")  # Humble's


def test_a_gid_is_the_xxh3_128_of_the_entitys_token_as_rmw_zenoh_computes_it():
    """Issue 41: rmw_zenoh's GID (``Entity::Entity``, liveliness_utils.cpp, every release
    0.2.0-0.12.0) is XXH3-128 of the entity's liveliness token, its low 64 bits then its
    high 64 bits, each little-endian, so it is what ``ros2 topic info -v`` shows for the
    bridge. The vectors: rmw_zenoh 0.2.10's C++ compiled and run on these tokens."""
    node = wire.Node(0, "8ff2a7b63c2c4cc2b1e07a3b4b2e4a11", "aesop_bridge", "/robot1")
    assert wire.gid(node.token()).hex() == "377a5510f79b8bb8d07cc9886cee64fd"
    publisher = node.entity_token(
        1, "MP", "chatter", "std_msgs/msg/String",
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
        wire.qos_keyexpr())
    assert publisher.endswith("/::,10:,:,:,,")
    assert wire.gid(publisher).hex() == "6a583461f8d873ca7fa8d4834a07da90"


def test_the_session_file_for_the_robots_nodes_keeps_rmw_zenohs_defaults(tmp_path):
    """Issue 41: the file replaces rmw_zenoh's default config whole; it held only mode,
    connect, scouting and auth, so timestamping was off (no BEST_EFFORT + TRANSIENT_LOCAL
    publisher could be made), and the 10-minute query timeout and 60 s lease were gone."""
    path = tmp_path / "ros2-session.json5"
    path.write_text(ros2_session_config("tcp/127.0.0.1:7447", "pw"))
    conf = zenoh.Config.from_file(str(path))  # what rmw_zenoh's zenoh-c reads
    got = {key: json.loads(conf.get_json(key)) for key in (
        "mode", "connect/endpoints", "timestamping/enabled", "queries_default_timeout",
        "transport/link/tx/lease", "transport/auth/usrpwd/user", "scouting/multicast/enabled")}
    assert got == {"mode": "client", "connect/endpoints": ["tcp/127.0.0.1:7447"],
                   "timestamping/enabled": {"router": True, "peer": True, "client": True},
                   "queries_default_timeout": 600000, "transport/link/tx/lease": 60000,
                   "transport/auth/usrpwd/user": "ros2", "scouting/multicast/enabled": False}
    assert wire.SESSION_DEFAULTS["mode"] == "peer"  # the defaults themselves are untouched
