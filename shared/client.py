"""The base of every service's typed HTTP client (``services/<service>/client.py``).

One ``httpx.AsyncClient`` per client, the bearer token on every request, and
one error type: a 4xx/5xx answer becomes :class:`ServiceError` carrying the
service's error envelope (``{"error": {"code", "message", "field"?}}``), a
connection failure stays an ``httpx.TransportError``.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from types import TracebackType
from typing import Any, TypeVar

import httpx
from pydantic import BaseModel

from .jobs import JobInfo

A = TypeVar("A", bound=BaseModel)


class ServiceError(Exception):
    """A service answered with an error: its status, code, message and field."""

    def __init__(self, method: str, path: str, status: int, code: str, message: str,
                 field: str | None = None) -> None:
        where = f" ({field})" if field else ""
        super().__init__(f"{method} {path} -> {status} {code}{where}: {message}")
        self.status, self.code, self.message, self.field = status, code, message, field


class ServiceClient:
    """``async with Client(url, token=...) as c``; subclasses add one method per route."""

    def __init__(self, base_url: str, *, token: str | None = None, timeout_s: float = 30.0,
                 transport: httpx.AsyncBaseTransport | None = None) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.AsyncClient(base_url=base_url, headers=headers, timeout=timeout_s,
                                      transport=transport)

    async def request(self, method: str, path: str, answer: type[A], *,
                      json: Any = None, params: dict[str, Any] | None = None,
                      expect: tuple[int, ...] = (200, 201)) -> A:
        """One route: the answer parsed as ``answer``, or :class:`ServiceError`."""
        response = await self.http.request(method, path, json=json, params=params)
        if response.status_code >= 400 or response.status_code not in expect:
            raise error_of(method, path, response)
        return answer.model_validate_json(response.content)

    async def close(self) -> None:
        await self.http.aclose()

    async def __aenter__(self: C) -> C:
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        await self.close()


C = TypeVar("C", bound=ServiceClient)
Progress = Callable[[JobInfo], None]


class JobClient(ServiceClient):
    """A client of a service with background jobs (``GET /v1/jobs/{id}``)."""

    async def job(self, job_id: str) -> JobInfo:
        return await self.request("GET", f"/v1/jobs/{job_id}", JobInfo)

    async def wait_for_job(self, job_id: str, *, progress: Progress | None = None,
                           poll_s: float = 0.5) -> JobInfo:
        """Poll until the job ends; a failed job raises its error as :class:`ServiceError`."""
        while True:
            job = await self.job(job_id)
            if progress is not None:
                progress(job)
            if job.state == "failed":
                error = job.error
                raise ServiceError("GET", f"/v1/jobs/{job_id}", 200,
                                   error.code if error else "failed",
                                   error.message if error else "the job failed",
                                   error.field if error else None)
            if job.state == "succeeded":
                return job
            await asyncio.sleep(poll_s)


def error_of(method: str, path: str, response: httpx.Response) -> ServiceError:
    """The :class:`ServiceError` for an answer, whatever its body."""
    code, message, field = "http_error", response.text[:500], None
    try:
        error = response.json().get("error")
    except (ValueError, AttributeError):
        error = None
    if isinstance(error, dict):
        code = str(error.get("code", code))
        message = str(error.get("message", message))
        field = error.get("field") if isinstance(error.get("field"), str) else None
    return ServiceError(method, path, response.status_code, code, message, field)
