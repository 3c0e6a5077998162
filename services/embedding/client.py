"""The vector-cache service's typed client: build, calibrate and query a cache over HTTP.

Every caller's way to the service: the demo, ``aesop bench bus``, the tests."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

from shared.client import JobClient, Progress
from shared.jobs import JobAccepted
from shared.messages import Detection

from .schemas import (
    Added,
    CacheInfo,
    CacheList,
    Calibrated,
    Deleted,
    Experience,
    Method,
    ProposalInfo,
    ProposalList,
    Scores,
)


class EmbeddingClient(JobClient):
    async def create_cache(self, name: str, *, model: str | None = None, k: int | None = None,
                           score: Literal["topk", "mahalanobis"] = "topk",
                           index: Literal["flat", "hnsw"] = "flat",
                           dim: int | None = None,
                           proposals: Literal["review", "auto"] | None = None) -> CacheInfo:
        """``PUT /v1/caches/{name}``: create it, or reconcile the existing one."""
        body: dict[str, Any] = {"score": score, "index": index}
        body |= {key: value for key, value in (("model", model), ("k", k), ("dim", dim),
                                               ("proposals", proposals))
                 if value is not None}
        return await self.request("PUT", f"/v1/caches/{name}", CacheInfo, json=body)

    async def cache(self, name: str) -> CacheInfo:
        return await self.request("GET", f"/v1/caches/{name}", CacheInfo)

    async def caches(self) -> list[CacheInfo]:
        return (await self.request("GET", "/v1/caches", CacheList)).caches

    async def add_texts(self, name: str, texts: Sequence[str], *, background: bool = False,
                        progress: Progress | None = None, poll_s: float = 0.5) -> Added:
        """Add nominal experiences (durable when this returns). ``background`` (or a
        ``progress`` callback, given each poll of the job) lets the service work as a job
        polled every ``poll_s``, so that no single request waits for a long build."""
        return await self.add_items(name, [{"text": t} for t in texts], background=background,
                                    progress=progress, poll_s=poll_s)

    async def add_items(self, name: str, items: Sequence[Mapping[str, Any]], *,
                        background: bool = False, progress: Progress | None = None,
                        poll_s: float = 0.5) -> Added:
        """:meth:`add_texts` with each item's ``id`` and ``metadata`` too."""
        body = {"items": list(items)}
        if not background and progress is None:
            return await self.request("POST", f"/v1/caches/{name}/experiences", Added, json=body)
        accepted = await self.request("POST", f"/v1/caches/{name}/experiences", JobAccepted,
                                      json=body, params={"wait": "false"}, expect=(202,))
        job = await self.wait_for_job(accepted.job, progress=progress, poll_s=poll_s)
        return Added.model_validate(job.result)

    async def calibrate(self, name: str, method: Method, *, alpha: float | None = None,
                        tpr: float | None = None,
                        calibration: Sequence[tuple[str, bool]] = (),
                        detections: Sequence[Sequence[Detection]] = (),
                        pairs: bool = False) -> Calibrated:
        """Compute tau; ``calibration`` is (text, is_anomaly) pairs for ``conformal`` and
        ``tpr-target``, ``detections`` each one's detections (or none); ``pairs``: score
        pairs of detections too."""
        body: dict[str, Any] = {"method": method} | ({"pairs": True} if pairs else {})
        body |= {key: value for key, value in (("alpha", alpha), ("tpr", tpr))
                 if value is not None}
        if calibration:
            found = detections or [()] * len(calibration)
            body["calibration"] = [
                {"text": text, "label": "anomaly" if bad else "nominal",
                 "detections": [d.model_dump(exclude_none=True) for d in seen]}
                for (text, bad), seen in zip(calibration, found, strict=True)]
        return await self.request("POST", f"/v1/caches/{name}/calibrate", Calibrated,
                                  json=body)

    async def score(self, name: str, texts: Sequence[str], k: int | None = None, *,
                    detections: Sequence[Sequence[Detection]] = ()) -> Scores:
        """Score ``texts``, each with its ``detections`` if given (one list per text)."""
        body: dict[str, Any] = {"texts": list(texts)} if not detections else {"queries": [
            {"text": text, "detections": [d.model_dump(exclude_none=True) for d in seen]}
            for text, seen in zip(texts, detections, strict=True)]}
        body |= {} if k is None else {"k": k}
        return await self.request("POST", f"/v1/caches/{name}/score", Scores, json=body)

    async def experience(self, name: str, ident: str) -> Experience:
        return await self.request("GET", f"/v1/caches/{name}/experiences/{ident}", Experience)

    async def proposals(self, name: str, state: str | None = None) -> ProposalList:
        params = {} if state is None else {"state": state}
        return await self.request("GET", f"/v1/caches/{name}/proposals", ProposalList,
                                  params=params)

    async def decide_proposal(self, name: str, ident: str, accept: bool) -> ProposalInfo:
        """Accept (add the scene as nominal) or reject a pending proposal."""
        verb = "accept" if accept else "reject"
        return await self.request("POST", f"/v1/caches/{name}/proposals/{ident}/{verb}",
                                  ProposalInfo)

    async def delete(self, name: str, ident: str) -> Deleted:
        return await self.request("DELETE", f"/v1/caches/{name}/experiences/{ident}", Deleted)
