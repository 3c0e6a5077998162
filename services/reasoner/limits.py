"""What one request may ask of the slow reasoner (text, options, deadline), on HTTP and bus alike.

The same checks over HTTP and on the bus: the observation's length, the number of options
and the deadline, against :class:`~.settings.ReasonerSettings` (``max_observation_chars``,
``max_options``, ``max_deadline_s``). The message's own shape is pydantic's to check; these
limits depend on the settings."""

from __future__ import annotations

import math
from collections.abc import Sequence

from shared.messages import Observation, Option

from .settings import ReasonerSettings

VARIABLE = "AESOP_REASONER_LIMITS__"  # a refusal names the variable that raises its limit


class LimitError(ValueError):
    """A request over a limit; ``field`` names what (``observation.text``, ``options``,
    ``deadline_s``), ``problem`` says how, and the message is ``"<field>: <problem>"``."""

    def __init__(self, field: str, problem: str) -> None:
        super().__init__(f"{field}: {problem}")
        self.field = field
        self.problem = problem


def check_request(settings: ReasonerSettings, *, observation: Observation | None,
                  options: Sequence[Option] | None, deadline_s: float | None) -> None:
    """Raise :class:`LimitError` for the first part over its limit; None skips a part.

    A deadline must be a positive, finite number of seconds: an infinite one would let
    the backends run with no timeout, and NaN compares false with every limit.
    """
    limits = settings.limits
    if observation is not None and len(observation.text) > limits.max_observation_chars:
        raise LimitError("observation.text", f"observation has {len(observation.text)} "
                         f"characters; the limit is {limits.max_observation_chars} "
                         f"({VARIABLE}MAX_OBSERVATION_CHARS)")
    if options is not None and len(options) > limits.max_options:
        raise LimitError("options", f"{len(options)} options; the limit is "
                         f"{limits.max_options} ({VARIABLE}MAX_OPTIONS)")
    if deadline_s is None:
        return
    if not math.isfinite(deadline_s):
        raise LimitError("deadline_s", f"deadline_s must be a finite number of seconds, "
                         f"got {deadline_s}")
    if deadline_s <= 0:
        raise LimitError("deadline_s", f"deadline_s must be positive, got {deadline_s:g}")
    if deadline_s > limits.max_deadline_s:
        raise LimitError("deadline_s", f"deadline_s {deadline_s} is over the limit "
                         f"{limits.max_deadline_s:g} ({VARIABLE}MAX_DEADLINE_S)")
