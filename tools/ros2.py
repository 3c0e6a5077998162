"""``aesop ros2``: the bridge to ROS 2 robots on rmw_zenoh (services/ros2).

``aesop ros2 keys --config FILE`` prints the Zenoh key expression of every mapped topic,
data keys first (inputs, then outputs), then the liveliness tokens the bridge declares
(``*`` for the session id, known once it runs): compare them with ``ros2 topic list -v``
or a ``z_sub``. ``aesop ros2 serve --config FILE`` runs the bridge (``aesop serve ros2``
with ``AESOP_ROS2_CONFIG``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tools.commands import ros2_config


def register(sub: argparse._SubParsersAction) -> None:
    ros2 = sub.add_parser("ros2", help="the bridge to ROS 2 robots on rmw_zenoh")
    rsub = ros2.add_subparsers(dest="ros2_command", required=True)
    keys = rsub.add_parser("keys", help="the Zenoh key of every mapped topic, one per line")
    keys.add_argument("--config", type=Path, required=True, help="the bridge's YAML file")
    keys.set_defaults(func=cmd_keys)
    serve = rsub.add_parser("serve", help="run the bridge (as `aesop serve ros2`)")
    serve.add_argument("--config", type=Path, default=None,
                       help="the bridge's YAML file (default: AESOP_ROS2_CONFIG)")
    serve.add_argument("--host", help="the address its HTTP API listens on (default "
                       "AESOP_ROS2_HOST, else 127.0.0.1)")
    serve.add_argument("--port", type=int, help="its HTTP port (default AESOP_ROS2_PORT, "
                       "else 8005)")
    serve.set_defaults(func=cmd_serve)


def key_lines(config) -> list[str]:
    """The data keys, then the node's and each entity's liveliness token."""
    from services.ros2 import convert, wire

    mapped = list(config.topics())
    hashes = [convert.topic_hash(m) for m in mapped]
    node = wire.Node(config.domain_id, "*", config.node, config.namespace)
    lines = [wire.data_key(config.domain_id, m.name, m.ros_type, h)
             for m, h in zip(mapped, hashes, strict=True)]
    lines.append(node.token())
    lines += [node.entity_token(m.entity_id, "MS" if m.direction == "in" else "MP", m.name,
                                m.ros_type, h, wire.qos_keyexpr(depth=m.settings.depth))
              for m, h in zip(mapped, hashes, strict=True)]
    return lines


def cmd_keys(args: argparse.Namespace) -> int:
    print("\n".join(key_lines(ros2_config(args.config))))
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    from tools.serve import serve_ros2

    overrides = {k: v for k, v in (("host", args.host), ("port", args.port),
                                   ("config", args.config)) if v is not None}
    return serve_ros2(overrides)
