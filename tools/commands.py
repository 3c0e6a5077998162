"""What the ``aesop`` command's modules share: the user error, output, flags, the Zenoh check.

Shared by :mod:`tools.cli` and the command modules it calls lazily, such as
:mod:`tools.recording.cli`: one error type for user
errors, one way to print a result, and one check that a Zenoh session can join the
network it is pointed at. A module of its own, so that the error raised by a command
module is the class ``aesop`` catches even when the CLI runs as ``__main__``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from shared.settings import BusSettings


class CliError(Exception):
    """A user error: printed without a traceback, exit status 2."""


def not_joined(exc: Exception) -> CliError:
    """A Zenoh session that could not open, with what a router that checks users needs."""
    return CliError(f"cannot join the Zenoh network ({exc}); a router that checks users "
                    "needs AESOP_ZENOH_MODE=client, AESOP_ZENOH_USER and "
                    "AESOP_ZENOH_PASSWORD(_FILE), e.g. the monitor user aesop up prints")


# how long the router (or peer) named has to let a command's session in before it gives up
JOIN_TIMEOUT_S = 5.0
# who to log in as at aesop up's router (what its ACL lets the command do), and the line
MONITOR_LOGIN = ("the read-only user monitor, as aesop up prints",
                 "AESOP_ZENOH_MODE=client AESOP_ZENOH_USER=monitor "
                 "AESOP_ZENOH_PASSWORD_FILE=<data-dir>/zenoh/monitor.password")
ROBOT_LOGIN = ("a robot's user, which may put its own observations and events "
               "(docs/recordings.md)",
               "AESOP_ZENOH_MODE=client AESOP_ZENOH_USER=robot-robot0 "
               "AESOP_ZENOH_PASSWORD_FILE=<data-dir>/zenoh/robot-robot0.password")
# aesop demo --attach logs in as the robot's user itself, from --data-dir or --secrets
DATA_DIR_LOGIN = ("the robot's user, from aesop up's data dir as aesop up prints (or "
                  "compose's --secrets)", "")


def joined(settings: BusSettings, command: str,
           login: tuple[str, str] = MONITOR_LOGIN) -> None:
    """Fail (a ``CliError``, status 2) unless the endpoints to connect to let a session in
    within ``JOIN_TIMEOUT_S``: a file named by the settings that cannot be read is named,
    and a router that refuses or does not answer is said, with how to log in as
    ``login`` (who, the variables) for ``aesop <command>``.

    A peer session (the default mode) opens whether or not its endpoints answer and keeps
    retrying them, so against aesop up's router, which lets in only its users, or where
    nothing listens, ``aesop watch``, ``record`` and ``replay`` used to wait silently for
    ever (replay publishing into nothing). This session is a probe of its own, closed once
    one router or peer is connected (any of several endpoints will do): the command's own
    session keeps zenoh's defaults. With no endpoints to connect to there is nothing to
    check (a peer that others connect to).
    """
    import time

    import zenoh

    from shared.bus import zenoh_config

    try:
        conf = zenoh_config(settings)
    except ValueError as exc:  # a file named by AESOP_ZENOH_* that cannot be read
        raise CliError(str(exc)) from None
    endpoints = json.loads(conf.get_json("connect/endpoints"))
    if not endpoints:
        return
    deadline = time.monotonic() + JOIN_TIMEOUT_S
    why = "no router or peer connected"
    try:
        with zenoh.open(conf) as session:  # a client that is refused raises here
            while not (list(session.info.routers_zid()) or list(session.info.peers_zid())):
                if time.monotonic() >= deadline:
                    break
                time.sleep(0.05)
            else:
                return
    except zenoh.ZError as exc:
        why = str(exc).split(" at /")[0].rstrip(". ")
    user = (f"as user {settings.zenoh_user}" if settings.zenoh_user is not None
            else "with no user (AESOP_ZENOH_USER unset)")
    who, line = login
    raise CliError(
        f"cannot join the Zenoh network {user}: the router at {', '.join(endpoints)} refused "
        f"this session or did not answer within {JOIN_TIMEOUT_S:g} s ({why}). aesop up's "
        f"router lets in only its own users; log in as {who}: "
        + " ".join(filter(None, (line, f"aesop {command} --connect ..."))))


def emit(result: dict[str, Any], as_json: bool) -> None:
    """One JSON object, or ``key  value`` lines."""
    if as_json:
        print(json.dumps(result, allow_nan=False))
        return
    width = max(len(k) for k in result)
    for key, value in result.items():
        shown = f"{value:.4f}" if isinstance(value, float) else value
        print(f"{key:<{width}}  {shown}")


DEFAULT_EMBEDDING_URL = "http://127.0.0.1:8001"  # aesop up's embedding service


def add_url_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", default=DEFAULT_EMBEDDING_URL,
                        help=f"the embedding service (default {DEFAULT_EMBEDDING_URL}); the "
                             "token from AESOP_ADMIN_TOKEN")


def control_scenario(path: Path | str | None, *, flag: bool = True):  # -> control's Scenario
    """The scene a command flies, or a usage error naming the file and field (and
    ``--scenario`` when the flag gave it, ``flag``)."""
    from services.control.core.scenario import ScenarioError, load_scenario

    try:
        return load_scenario(path)
    except (ScenarioError, OSError) as exc:
        raise CliError(f"--scenario: {exc}" if flag else str(exc)) from None


def ros2_config(path: Path | None, *,
                frame: str | None = None):  # -> services.ros2.config.BridgeConfig
    """The ROS 2 bridge's config at ``path``, or a usage error naming what is wrong;
    ``frame``: the frame control flies in, which the odometry's must be."""
    from services.ros2.config import ConfigError, load_config

    if path is None:
        raise CliError("the bridge needs its config: --config FILE or AESOP_ROS2_CONFIG "
                       "(deploy/ros2/quadrotor.yaml is the quadrotor's)")
    try:
        return load_config(path, frame=frame)
    except ConfigError as exc:
        raise CliError(str(exc)) from None
