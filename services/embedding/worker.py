"""Zenoh worker: observations in, anomaly verdicts out.

Subscribes ``aesop/*/observation``; every observation is scored against the
detector cache through the service's micro-batcher (concurrent observations
share one embedding call) and answered with an ``AnomalyVerdict`` on
``aesop/{robot}/anomaly``. An uncalibrated cache answers "anomaly" (fail-safe).
With detector replicas sharing a PostgreSQL store, each scores only its own robots
(rendezvous hashing over the live replicas, :mod:`.fleet.replicas`), so an observation is
answered once. Observations wait per robot and are scored in turn (:mod:`.fairness`): a robot past
its rate is refused before its message is decoded, and a robot has one observation being
scored at a time, so it has at most one in any embedding batch, and one robot's flood
(distinct texts or not) neither drops another's verdicts nor delays them by more than
one of its embeddings (an observation whose vectors the detector knows already, by none:
it is scored beside the embeddings, :mod:`.scorer`); refusals are counted per robot
(``aesop_embedding_observations_dropped_total``) and said, at most every 10 s, in an
``observations_dropped`` alarm on that robot's event key.

It also learns from the slow reasoner (:mod:`.detector.proposals`): it remembers the
observations it flagged and the reasoner requests it sees, and when an LLM's decision
(never a fallback) answers "continue" to a request that offered it, for an observation
this worker flagged, the observation is proposed to the detector cache. Each proposal
made, counted, accepted or rejected is published as an ``Event`` (kind
``proposal_<what>``) on ``aesop/{robot}/event/embedding``.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from shared import topics
from shared.bus import Bus, Received, Subscription
from shared.messages import (
    AnomalyVerdict,
    Drift,
    Event,
    Observation,
    ReasonerDecision,
    ReasonerRequest,
)
from shared.pump import MessagePump

from .detector.drift import DriftMonitor, DriftReport
from .detector.errors import DetectorError
from .detector.proposals import Proposal, scene_id
from .fairness import OTHER, DropReports, FairInbox, Reason
from .fleet.replicas import Replicas
from .scorer import ScoreBatch
from .service import CacheService
from .settings import EmbeddingSettings

log = logging.getLogger(__name__)

SOURCE = "embedding"  # its events' source, and the last part of their key
REMEMBERED = 1024  # flagged observations and reasoner requests kept to match decisions
DROPS_EVERY_S = 10.0  # at most one observations_dropped alarm per robot this often
WHY = {"rate": "over its rate (AESOP_EMBEDDING_LIMITS__ROBOT_HZ)",
       "full": "superseded while its queue was full",
       "robots": "from robots past AESOP_EMBEDDING_LIMITS__MAX_ROBOTS"}


def make_verdict(obs: Observation, robot: str, batch: ScoreBatch, cache: str,
                 latency_ms: float, drift: Drift | None = None) -> AnomalyVerdict:
    """h(o_t) as the cache judged it (``Cache.judge``); no tau yet -> anomaly, with the
    reason."""
    scored = batch.results[0]
    reason = None
    if scored.is_anomaly is None:
        is_anomaly, reason = True, "cache not calibrated: fail-safe anomaly"
    else:
        is_anomaly = scored.is_anomaly
        if batch.stale:
            reason = "calibration is stale: experiences changed since it was computed"
    return AnomalyVerdict(
        robot=robot, seq=obs.seq, score=scored.score, threshold=batch.threshold,
        is_anomaly=is_anomaly, k=batch.k, neighbors=scored.neighbors, model=batch.model or "",
        cache=cache, cache_version=batch.version, latency_ms=latency_ms, reason=reason,
        p_value=scored.p_value, detections=scored.matches, pair=scored.pair, drift=drift)


class DetectorWorker:
    def __init__(self, service: CacheService, bus: Bus, *, cache: str,
                 max_in_flight: int = 256, metrics: Any = None, owns_bus: bool = False,
                 max_text_chars: int = 4000, robot_hz: float = 25.0,
                 max_robots: int = 256, drift: DriftMonitor | None = None,
                 replicas: Replicas | None = None) -> None:
        """``replicas``: this replica among others, scoring only its own robots
        (:mod:`.fleet.replicas`); None: every robot."""
        self.service = service
        self.replicas = replicas
        # a replica warms its model up before it declares itself and takes robots: /readyz
        # says not ready meanwhile (compose's healthcheck, a supervisor, a load balancer)
        self.warming = replicas is not None
        # as over HTTP (AESOP_EMBEDDING_LIMITS__MAX_TEXT_CHARS)
        self.max_text_chars = max_text_chars
        self.bus = bus
        self.owns_bus = owns_bus
        self.cache = cache
        self.metrics = metrics
        self.max_in_flight = max_in_flight
        self.inbox: FairInbox[Received[Observation]] = FairInbox(rate_hz=robot_hz,
                                                                 max_robots=max_robots)
        self.drift = drift if drift is not None else DriftMonitor(max_robots=max_robots)
        if metrics is not None:
            metrics.dropped.source = self.inbox.counts
            metrics.drifting.source = self.drift.drifting
        self._scoring: set[asyncio.Task[None]] = set()
        self._observations: Subscription[Observation] | None = None
        self._reports = DropReports(DROPS_EVERY_S)
        self._last_alarm = 0.0
        # (robot, seq) -> the flagged observation and its verdict; request id -> request
        self._flagged: OrderedDict[tuple[str, int], tuple[Observation, AnomalyVerdict]] = \
            OrderedDict()
        self._requests: OrderedDict[str, ReasonerRequest] = OrderedDict()
        self._learning: list[MessagePump[Any]] = [
            MessagePump(bus, topics.reasoner_request(topics.ANY_ROBOT), ReasonerRequest,
                        self._remember_request, max_in_flight=8, maxsize=256),
            MessagePump(bus, topics.reasoner_decision(topics.ANY_ROBOT), ReasonerDecision,
                        self._learn, max_in_flight=8, maxsize=256),
        ]
        service.review.listeners.append(self._proposal_event)

    @classmethod
    def factory(cls, settings: EmbeddingSettings) -> Callable[[CacheService, Any], DetectorWorker]:
        """For ``create_app``: open a Zenoh session in the lifespan; the worker owns it."""

        def make(service: CacheService, metrics: Any) -> DetectorWorker:
            bus = Bus.open(settings, "embedding")
            limits, adapt = settings.limits, settings.adapt
            return cls(service, bus, cache=settings.detector_cache, metrics=metrics,
                       owns_bus=True, max_text_chars=limits.max_text_chars,
                       robot_hz=limits.robot_hz, max_robots=limits.max_robots,
                       drift=DriftMonitor(adapt.drift_window, adapt.drift_significance,
                                          limits.max_robots),
                       replicas=Replicas(settings.replica_name()))

        return make

    async def run(self) -> None:
        if self.replicas is not None:
            await self._warm_up()  # before it takes any robot from the others
            self.replicas.join(self.bus.session)
            self.warming = False
        reporting = asyncio.create_task(self._report_drops())
        try:
            await asyncio.gather(self._receive(), *(pump.run() for pump in self._learning))
        finally:
            reporting.cancel()

    async def _warm_up(self) -> None:
        """Load the detector cache's model (the service's default before the cache
        exists) and embed once: a replica that joins, or takes a dead one's robots, answers
        its first observations as fast as the next ones (exporting and loading the model
        took 10-60 s, and the robots' loops saw their verdicts go stale meanwhile)."""
        try:
            model = self.service.entry(self.cache).cache.config.model
        except DetectorError:
            model = self.service.settings.model
        if model is None:
            return
        try:
            embedder = await self.service.scorer.embedder(model)
            await self.service.scorer.on_compute(embedder.embed, ["warming up"])
        except DetectorError as exc:
            log.warning("model %s not loaded before taking robots: %s", model, exc.message)

    async def stop(self) -> None:
        if self._observations is not None:
            self._observations.close()
        if self._scoring:
            await asyncio.gather(*self._scoring, return_exceptions=True)
        for pump in self._learning:
            await pump.stop()
        if self.replicas is not None:
            self.replicas.leave()
        if self._proposal_event in self.service.review.listeners:
            self.service.review.listeners.remove(self._proposal_event)
        if self.owns_bus:
            self.bus.close()

    def _admit(self, key: str) -> bool:
        """On a Zenoh thread, before decoding: this replica's robot, within its rate?"""
        try:
            robot = topics.robot_of(key)
        except ValueError:
            return False
        if self.replicas is not None and not self.replicas.owns(robot):
            return False  # another replica's: it answers
        return self.inbox.admit(robot) is None

    async def _receive(self) -> None:
        """Observations into the per-robot inbox as they arrive (this never waits for
        scoring, so the subscription's own queue never backs up), scored in turn."""
        self._observations = self.bus.subscribe(
            topics.observation(topics.ANY_ROBOT), Observation, maxsize=1024,
            on_error=self._undecodable, admit=self._admit)
        async for received in self._observations:
            self.inbox.put(topics.robot_of(received.key), received)
            self._dispatch()

    def _dispatch(self) -> None:
        while len(self._scoring) < self.max_in_flight:
            nxt = self.inbox.take()
            if nxt is None:
                return
            robot, received = nxt
            task = asyncio.create_task(self._handle(received))
            self._scoring.add(task)
            task.add_done_callback(functools.partial(self._scored, robot=robot))

    def _scored(self, task: asyncio.Task[None], *, robot: str) -> None:
        self._scoring.discard(task)
        self.inbox.done(robot)
        if not task.cancelled() and task.exception() is not None:
            log.error("scoring an observation of %s failed", robot, exc_info=task.exception())
        if self._observations is not None and not self._observations.closed:
            self._dispatch()

    async def _report_drops(self) -> None:
        """Say the refusals (:class:`.fairness.DropReports`), looking once a second."""
        while True:
            await asyncio.sleep(1.0)
            for robot, reasons in self._reports.due(self.inbox.counts(),
                                                    time.monotonic()).items():
                self._say_dropped(robot, reasons)

    def _say_dropped(self, robot: str, reasons: dict[Reason, int]) -> None:
        said = ", ".join(f"{n} {WHY[reason]}" for reason, n in sorted(reasons.items()))
        message = f"observations of {robot} not scored: {said}"
        log.warning("%s", message)
        if robot == OTHER:  # no robot to tell: the log and the metric say it
            return
        self.bus.publish(topics.event(robot, SOURCE), Event(
            robot=robot, source=SOURCE, kind="observations_dropped", severity="alarm",
            message=message, data=dict(reasons)))

    async def _handle(self, received: Received[Observation]) -> None:
        start = time.perf_counter()
        obs = received.message
        robot = topics.robot_of(received.key)
        if len(obs.text) > self.max_text_chars:  # no verdict: the loop sees silence
            if self.metrics is not None:
                self.metrics.bus_rejected.labels("text").inc()
            self._alarm(robot, f"observation {obs.seq} has {len(obs.text)} characters; the "
                        f"limit is {self.max_text_chars} "
                        "(AESOP_EMBEDDING_LIMITS__MAX_TEXT_CHARS): not scored")
            return
        try:
            batch = await self.service.scorer.score_texts(self.cache, [obs.text], urgent=True,
                                                   detections=[obs.detections])
        except DetectorError as exc:
            self._alarm(robot, f"cannot score observation {obs.seq}: {exc.message}")
            return
        except Exception:
            log.exception("scoring observation %s of %s failed", obs.seq, robot)
            return
        scored = batch.results[0]
        flagged = scored.is_anomaly is not False
        report = self.drift.observe(robot, flagged, None if batch.alpha is None or
                                    scored.is_anomaly is None else 1.0 - batch.alpha,
                                    [m.detection for m in scored.matches], scene_id(obs))
        now = self.drift.current(robot)
        verdict = make_verdict(obs, robot, batch, self.cache,
                               (time.perf_counter() - start) * 1000,
                               None if now is None else Drift(flagged=now[0], seen=now[1],
                                                              phrases=now[2]))
        self.bus.publish(topics.anomaly(robot), verdict)
        if report is not None:
            self._say_drift(robot, report)
        if verdict.is_anomaly:
            remember(self._flagged, (robot, obs.seq), (obs, verdict))
        if self.metrics is not None:
            self.metrics.verdicts.labels(str(verdict.is_anomaly).lower()).inc()

    async def _remember_request(self, received: Received[ReasonerRequest]) -> None:
        remember(self._requests, received.message.request_id, received.message)

    async def _learn(self, received: Received[ReasonerDecision]) -> None:
        """Propose the flagged observation an LLM answered "continue" for."""
        decision = received.message
        if decision.source != "llm" or decision.choice != 0:
            return
        request = self._requests.pop(decision.request_id, None)
        if request is None or not any(o.index == 0 for o in request.options):
            return
        robot = topics.robot_of(received.key)
        flagged = self._flagged.get((robot, request.observation.seq))
        if flagged is None or flagged[0].text != request.observation.text:
            return  # not an observation this detector flagged (e.g. silence)
        obs, verdict = flagged
        try:
            await self.service.review.propose(
                self.cache, obs.model_copy(update={"robot": robot}),
                request_id=decision.request_id, model=decision.model,
                rationale=decision.rationale, score=verdict.score, p_value=verdict.p_value,
                now=time.time())
        except DetectorError as exc:
            log.warning("observation %s of %s not proposed: %s", obs.seq, robot, exc.message)

    def _proposal_event(self, what: str, proposal: Proposal) -> None:
        """``proposal_proposed|accepted|rejected`` on the proposing robot's event key."""
        named = proposal.text if len(proposal.text) <= 200 else proposal.text[:199] + "…"
        self.bus.publish(topics.event(proposal.robot, SOURCE), Event(
            robot=proposal.robot, source=SOURCE, kind=f"proposal_{what}",
            message=f"{self.cache}: a scene the reasoner let pass was {what} as nominal "
                    f"({proposal.count}×): {' / '.join(named.splitlines())}",
            data={"cache": self.cache, "id": proposal.id, "state": proposal.state,
                  "count": proposal.count, "text": proposal.text[:1000],
                  "model": proposal.model, "flag": proposal.flag}))

    def _say_drift(self, robot: str, report: DriftReport) -> None:
        """``drift`` (a warning) or ``drift_cleared`` on the robot's event key."""
        log.warning("%s: %s", robot, report.message)
        self.bus.publish(topics.event(robot, SOURCE), Event(
            robot=robot, source=SOURCE, kind="drift" if report.state == "drift" else
            "drift_cleared", severity="warning" if report.state == "drift" else "info",
            message=report.message, data={
                "cache": self.cache, "flagged": report.flagged, "seen": report.seen,
                "expected_rate": report.expected_rate, "p_value": report.p_value,
                "phrases": "; ".join(report.phrases)}))

    def _undecodable(self) -> None:  # on a Zenoh thread; the bus logs it, rate-limited
        if self.metrics is not None:
            self.metrics.bus_rejected.labels("message").inc()

    def _alarm(self, robot: str, message: str) -> None:
        """At most one alarm event per 10 s; the control loop sees missing verdicts as stale."""
        now = time.monotonic()
        if now - self._last_alarm < 10.0:
            return
        self._last_alarm = now
        log.warning("%s", message)
        self.bus.publish(topics.event(robot, SOURCE), Event(
            robot=robot, source=SOURCE, kind="detector_unavailable", severity="alarm",
            message=message))


def remember(kept: OrderedDict[Any, Any], key: Any, value: Any) -> None:
    """Keep ``value`` under ``key``, forgetting the oldest past :data:`REMEMBERED`."""
    kept[key] = value
    kept.move_to_end(key)
    while len(kept) > REMEMBERED:
        kept.popitem(last=False)
