"""Progress of long operations (``GET /v1/jobs/{id}``), kept in memory per service."""

from __future__ import annotations

import time
import uuid
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict


class UnknownJob(KeyError):
    """No job with this id (or it was forgotten: only the newest ``keep`` finished ones
    are kept)."""


@dataclass
class Job:
    """Progress of a long operation (``GET /v1/jobs/{id}``)."""

    id: str
    kind: str
    cache: str
    total: int
    done: int = 0
    state: Literal["running", "succeeded", "failed"] = "running"
    result: dict[str, Any] | None = None
    error: dict[str, Any] | None = None
    created_at: float = field(default_factory=time.time)
    finished_at: float | None = None

    def progress(self, done: int, total: int) -> None:
        self.done, self.total = done, total

    def succeed(self, result: dict[str, Any]) -> None:
        self.state, self.result, self.finished_at = "succeeded", result, time.time()

    def fail(self, code: str, message: str, field: str | None = None) -> None:
        self.state, self.finished_at = "failed", time.time()
        self.error = {"code": code, "message": message, "field": field}

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in (
            "id", "kind", "cache", "total", "done", "state", "result", "error",
            "created_at", "finished_at")}


class TooManyJobs(Exception):
    """``max_running`` jobs are running already (answer 429 naming ``setting``)."""

    def __init__(self, limit: int, setting: str) -> None:
        super().__init__(f"{limit} jobs are running already, the limit ({setting}): "
                         "retry when one has finished")
        self.limit, self.setting = limit, setting


class Jobs:
    """The jobs of a service: at most ``max_running`` running (:class:`TooManyJobs`
    past it), and the newest ``keep`` finished ones; a running job is never forgotten."""

    def __init__(self, keep: int = 1000, max_running: int = 16,
                 setting: str = "max_running") -> None:
        self._jobs: OrderedDict[str, Job] = OrderedDict()
        self._keep, self._max_running, self._setting = keep, max_running, setting

    def create(self, kind: str, cache: str, total: int) -> Job:
        if sum(job.state == "running" for job in self._jobs.values()) >= self._max_running:
            raise TooManyJobs(self._max_running, self._setting)
        job = Job(uuid.uuid4().hex, kind, cache, total)
        self._jobs[job.id] = job
        finished = [j.id for j in self._jobs.values() if j.state != "running"]
        for job_id in finished[:max(0, len(finished) - self._keep)]:
            del self._jobs[job_id]
        return job

    def get(self, job_id: str) -> Job:
        try:
            return self._jobs[job_id]
        except KeyError:
            raise UnknownJob(job_id) from None


class _Answer(BaseModel):
    model_config = ConfigDict(extra="ignore")


class JobAccepted(_Answer):
    """The work goes on in the background: poll ``GET /v1/jobs/{job}``."""

    job: str
    state: Literal["running", "succeeded", "failed"]
    total: int

    @classmethod
    def of(cls, job: Job) -> JobAccepted:
        return cls(job=job.id, state=job.state, total=job.total)


class JobError(_Answer):
    code: str
    message: str
    field: str | None = None


class JobInfo(_Answer):
    """``GET /v1/jobs/{id}``."""

    id: str
    kind: str
    cache: str  # what the job works on: a cache, or a reasoner backend
    total: int
    done: int
    state: Literal["running", "succeeded", "failed"]
    result: dict[str, Any] | None = None  # the answer of the work, once succeeded
    error: JobError | None = None
    created_at: float
    finished_at: float | None = None

    @classmethod
    def of(cls, job: Job) -> JobInfo:
        return cls.model_validate(job.to_dict())
