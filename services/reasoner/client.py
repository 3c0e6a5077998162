"""The slow-reasoner service's typed client (tests, and anyone asking by HTTP)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

from shared.client import JobClient
from shared.jobs import JobAccepted
from shared.messages import Observation, Option, ReasonerDecision

from .schemas import Backends


class ReasonerClient(JobClient):
    async def reason(self, observation: Observation, options: Sequence[Option], deadline_s: float,
                     request_id: str | None = None) -> ReasonerDecision:
        """A decision by ``deadline_s``: the LLM's, or the fallback's (``source`` says)."""
        body: dict[str, Any] = {
            "observation": observation.model_dump(mode="json"),
            "options": [o.model_dump(mode="json") for o in options], "deadline_s": deadline_s}
        if request_id is not None:
            body["request_id"] = request_id
        return await self.request("POST", "/v1/reason", ReasonerDecision, json=body)

    async def calibrate_latency(self, *, n: int = 100, warmup: int = 3, quantile: float = 0.95,
                                confidence: float = 0.95, timeout_s: float = 30.0,
                                backend: Literal["primary", "hedge"] = "primary",
                                observation: Observation | None = None,
                                options: Sequence[Option] | None = None) -> JobAccepted:
        """Start measuring a backend's latency (a job: :meth:`wait_for_job` gives K), asked
        ``observation`` with ``options`` (default: the service's red-box scene)."""
        body: dict[str, Any] = {"n": n, "warmup": warmup, "quantile": quantile,
                                "confidence": confidence, "timeout_s": timeout_s,
                                "backend": backend}
        if observation is not None:
            body["observation"] = observation.model_dump(mode="json")
        if options is not None:
            body["options"] = [o.model_dump(mode="json") for o in options]
        return await self.request("POST", "/v1/latency/calibrate", JobAccepted, json=body,
                                  expect=(202,))

    async def backends(self) -> Backends:
        return await self.request("GET", "/v1/backends", Backends)
