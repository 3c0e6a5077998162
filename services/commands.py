"""What the ``aesop`` command's modules share (:mod:`services.cli` and the command
modules it calls lazily, such as :mod:`services.recording.cli`): one error type for user
errors and one way to print a result. A module of its own, so that the error raised by a
command module is the class ``aesop`` catches even when the CLI runs as ``__main__``.
"""

from __future__ import annotations

import json
from typing import Any


class CliError(Exception):
    """A user error: printed without a traceback, exit status 2."""


def not_joined(exc: Exception) -> CliError:
    """A Zenoh session that could not open, with what a router that checks users needs."""
    return CliError(f"cannot join the Zenoh network ({exc}); a router that checks users "
                    "needs AESOP_ZENOH_MODE=client, AESOP_ZENOH_USER and "
                    "AESOP_ZENOH_PASSWORD(_FILE), e.g. the monitor user aesop up prints")


def emit(result: dict[str, Any], as_json: bool) -> None:
    """One JSON object, or ``key  value`` lines."""
    if as_json:
        print(json.dumps(result, allow_nan=False))
        return
    width = max(len(k) for k in result)
    for key, value in result.items():
        shown = f"{value:.4f}" if isinstance(value, float) else value
        print(f"{key:<{width}}  {shown}")
