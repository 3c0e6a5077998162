"""The vector-cache service's own Prometheus metrics (beside the HTTP ones)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from .service import CacheService


class EmbeddingMetrics:
    def __init__(self, registry: CollectorRegistry, service: CacheService) -> None:
        self.score_seconds = Histogram(
            "aesop_embedding_score_seconds", "Score request latency (embed + search + threshold)",
            registry=registry, buckets=(.002, .005, .01, .015, .02, .03, .05, .1, .25, .5, 1, 5))
        self.batch_size = Histogram(
            "aesop_embedding_batch_size", "Texts per micro-batched embedding call",
            registry=registry, buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256))
        self.follow_lag = Histogram(
            "aesop_embedding_follow_lag_seconds", "With a shared store: from another "
            "replica's commit to its change applied here",
            registry=registry, buckets=(.005, .01, .025, .05, .1, .25, .5, 1, 2.5, 5, 10))
        self.verdicts = Counter("aesop_embedding_verdicts", "Anomaly verdicts published",
                                ["anomaly"], registry=registry)
        self.bus_rejected = Counter(
            "aesop_embedding_bus_rejected", "Observations on the bus not scored: a field over "
            "its HTTP limit (no verdict answers them; the control loop sees silence)",
            ["field"], registry=registry)
        self.dropped = Dropped()
        registry.register(self.dropped)
        self.drifting = Drifting()
        registry.register(self.drifting)
        size = Gauge("aesop_embedding_cache_size", "Experiences per cache", ["cache"],
                     registry=registry)
        self.size = size
        self.service = service

    def refresh(self) -> None:
        for name in self.service.names():
            self.size.labels(name).set(self.service.entry(name).cache.size)


class Dropped(Collector):
    """``aesop_embedding_observations_dropped_total{robot, reason}``, read at scrape time
    from the bus worker's inbox (its robots are bounded, so are the labels)."""

    def __init__(self) -> None:
        self.source: Callable[[], Mapping[tuple[str, str], int]] | None = None

    def collect(self) -> Iterator[CounterMetricFamily]:
        family = CounterMetricFamily(
            "aesop_embedding_observations_dropped", "Observations on the bus not scored, "
            "per robot: over its rate, superseded in its full queue, or past the robots "
            "tracked", labels=["robot", "reason"])
        for (robot, reason), n in sorted((self.source() if self.source else {}).items()):
            family.add_metric([robot, reason], n)
        yield family


class Drifting(Collector):
    """``aesop_embedding_drifting{robot}``: 1 for each robot whose verdicts flag more than
    the calibration allows (:mod:`.detector.drift`), read at scrape time from the bus worker."""

    def __init__(self) -> None:
        self.source: Callable[[], list[str]] | None = None

    def collect(self) -> Iterator[GaugeMetricFamily]:
        family = GaugeMetricFamily(
            "aesop_embedding_drifting", "Robots whose recent verdicts flag more than the "
            "calibration allows (drift: new wording?), 1 each", labels=["robot"])
        for robot in self.source() if self.source else []:
            family.add_metric([robot], 1.0)
        yield family
