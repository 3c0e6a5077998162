"""In-process chat backends for tests of the decider (no server): one that answers at
once and counts its calls, one that never answers until cancelled."""

from __future__ import annotations

import asyncio
from typing import Any

from services.reasoner.backends import Completion


class Recording:
    """A backend that counts its calls and always answers 1."""

    name = model = "recording"

    def __init__(self) -> None:
        self.calls = 0

    async def complete(self, messages: list[dict[str, str]], *,
                       stop_when: Any = None, answers: Any = None) -> Completion:
        self.calls += 1
        return Completion(text="FINAL ANSWER: 1\n", prompt_tokens=None,
                          completion_tokens=None, stopped_early=False)

    async def aclose(self) -> None:
        pass


class Stalling:
    """A backend that never answers (until cancelled)."""

    name = model = "stall"

    async def complete(self, messages: list[dict[str, str]], *,
                       stop_when: Any = None, answers: Any = None) -> Completion:
        await asyncio.sleep(3600)
        raise AssertionError("not reached")

    async def aclose(self) -> None:
        pass
