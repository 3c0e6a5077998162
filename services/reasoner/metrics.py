"""The slow reasoner's own Prometheus metrics (beside the HTTP ones)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Histogram

from shared.messages import ReasonerDecision

from .backends import Completion


class ReasonerMetrics:
    def __init__(self, registry: CollectorRegistry) -> None:
        self.latency = Histogram(
            "aesop_reasoner_decision_seconds", "Time from request to decision",
            ["source"], registry=registry,
            buckets=(.05, .1, .25, .5, 1, 1.5, 2, 3, 4, 5, 7.5, 10, 20))
        self.decisions = Counter("aesop_reasoner_decisions", "Decisions by source",
                                 ["source"], registry=registry)

        self.tokens = Counter("aesop_reasoner_tokens", "LLM tokens, as the server reports them "
                              "in 'usage' (streamed answers count only where it does)",
                              ["kind"], registry=registry)
        self.bus_rejected = Counter(
            "aesop_reasoner_bus_rejected", "Requests on the bus dropped, unanswered, for a "
            "field over its limit (max_observation_chars, max_options, max_deadline_s)",
            ["field"], registry=registry)
        self.keepers_started = Counter("aesop_reasoner_keeper_starts",
                                       "Deadline keepers started", registry=registry)
        self.keepers_lost = Counter(
            "aesop_reasoner_keeper_lost", "Deadline keepers lost: exited (killed, crashed, "
            "or failed to start) or stalled (no heartbeat for 0.25 s: stopped or starved; "
            "then killed)", ["why"], registry=registry)
        self.sent_by_service = Counter(
            "aesop_reasoner_sent_by_service", "Decisions the service sent itself, on its "
            "own Zenoh session, for requests no deadline keeper could answer", ["source"],
            registry=registry)
        self.dropped_late = Counter(
            "aesop_reasoner_dropped_late", "Decisions not sent because they would have left "
            "after their request's deadline (the robot takes its own fallback at K), by "
            "sender: the keeper or the service", ["sender"], registry=registry)
        for why in ("exited", "stalled"):
            self.keepers_lost.labels(why)
        for sender in ("keeper", "service"):
            self.dropped_late.labels(sender)

    def keeper_started(self) -> None:
        self.keepers_started.inc()

    def keeper_lost(self, why: str) -> None:
        self.keepers_lost.labels(why).inc()

    def count(self, completion: Completion) -> None:
        if completion.prompt_tokens:
            self.tokens.labels("prompt").inc(completion.prompt_tokens)
        if completion.completion_tokens:
            self.tokens.labels("completion").inc(completion.completion_tokens)

    def reject(self, field: str) -> None:
        self.bus_rejected.labels(field).inc()

    def observe(self, decision: ReasonerDecision) -> None:
        self.decisions.labels(decision.source).inc()
        self.latency.labels(decision.source).observe(decision.latency_ms / 1000)
