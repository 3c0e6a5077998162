"""shared/: messages round-trip and refuse bad fields; topics; settings from the environment."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from shared import topics
from shared.messages import (
    AnomalyVerdict,
    ControlState,
    Event,
    Neighbor,
    Observation,
    Option,
    PairMatch,
    PlanSnapshot,
    ReasonerDecision,
    ReasonerRequest,
)
from shared.process import ephemeral_range, free_port
from shared.settings import ServiceSettings
from tools.stack.up import Ports

OBS = Observation(robot="r1", seq=3, task="land", text="a red box on the ground")
PAIR = PairMatch(detections=("a red box", "a person"), nearest=("a red box", "a drill"),
                 similarity=0.41, p_value=0.02)
MESSAGES = [
    OBS,
    AnomalyVerdict(seq=3, score=-0.9, threshold=-0.95, is_anomaly=True, k=1, model="m",
                   cache="c", cache_version=4, latency_ms=12.5,
                   neighbors=(Neighbor(id="a", text="t", similarity=0.9),), p_value=0.01,
                   pair=PAIR),
    ReasonerRequest(request_id="q1", observation=OBS, deadline_s=4.3,
                    options=(Option(index=0, label="continue"), Option(index=1, label="hold")),
                    unusual_pair=PAIR),
    ReasonerDecision(request_id="q1", choice=1, source="timeout", latency_ms=4300.0),
    ControlState(t=1.0, x=tuple([0.0] * 12), u=(9.81, 0, 0, 0), mode="anomaly_pending"),
    PlanSnapshot(t=1.0, nominal=((0, 0, 1),), recovery={1: ((1, 1, 0),)}, consensus_steps=15,
                 solve_ms=4.2, status="solved"),
    Event(source="embedding", kind="alarm", severity="alarm", data={"n": 1}),
]


@pytest.mark.parametrize("message", MESSAGES, ids=lambda m: type(m).__name__)
def test_messages_round_trip_as_json(message: object) -> None:
    cls = type(message)
    assert cls.decode(message.encode()) == message  # type: ignore[attr-defined]
    assert message.schema_version == 1  # type: ignore[attr-defined]


def test_messages_are_frozen_and_strict() -> None:
    with pytest.raises(ValidationError):
        OBS.seq = 4  # type: ignore[misc]
    with pytest.raises(ValidationError):
        Observation.decode(b'{"seq": 1, "text": "x", "surprise": true}')
    with pytest.raises(ValidationError):
        Observation(seq=-1, text="x")
    with pytest.raises(ValidationError):
        ControlState(t=0, x=(0.0,) * 11, u=(0.0,) * 4, mode="nominal")
    with pytest.raises(ValidationError):
        AnomalyVerdict(seq=0, score=math.nan, threshold=None, is_anomaly=True, k=1, model="m",
                       cache="c", cache_version=0, latency_ms=0)
    with pytest.raises(ValidationError):
        ReasonerDecision(request_id="q", choice=0, source="guess", latency_ms=0)  # type: ignore[arg-type]


def test_topics() -> None:
    assert topics.observation("robot0") == "aesop/robot0/observation"
    assert topics.reasoner_decision("r") == "aesop/r/reasoner/decision"
    assert topics.anomaly(topics.ANY_ROBOT) == "aesop/*/anomaly"
    assert topics.health("embedding") == "aesop/health/embedding"
    assert topics.robot_of("aesop/drone-7/observation") == "drone-7"
    with pytest.raises(ValueError):
        topics.observation("a/b")
    with pytest.raises(ValueError):
        topics.robot_of("aesop/health/embedding")


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AESOP_ZENOH_CONNECT", "tcp/127.0.0.1:7447, tcp/127.0.0.1:7448")
    monkeypatch.setenv("AESOP_PORT", "9001")
    monkeypatch.setenv("AESOP_ADMIN_TOKEN", "")
    s = ServiceSettings()
    assert s.zenoh_connect == ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"]
    assert s.port == 9001 and s.admin_token is None
    s.check_exposure()  # loopback without a token is fine
    with pytest.raises(ValueError, match="AESOP_ADMIN_TOKEN"):
        ServiceSettings(host="0.0.0.0").check_exposure()
    ServiceSettings(host="0.0.0.0", admin_token="x" * 16).check_exposure()
    with pytest.raises(ValidationError, match="at least 16"):
        ServiceSettings(admin_token="short")


@pytest.mark.parametrize("payload", [
    b'{"seq": 1, "text": "' + b"x" * 16_001 + b'"}',  # a text past the bus's ceiling
    b'{"seq": 1, "text": "x", "task": "' + b"t" * 1_001 + b'"}',
    b'{"seq": 1, "text": "x", "detections": [' + b",".join([b'{"label": "a"}'] * 65) + b"]}",
    b'{"seq": 1, "text": "x", "detections": [{"label": "' + b"l" * 201 + b'"}]}',
    b'{"seq": 1, "text": "x", "stamp": Infinity}',
], ids=["text", "task", "detections", "label", "stamp"])
def test_the_bus_refuses_observations_past_its_limits(payload: bytes) -> None:
    """Issue 14: the bus path skipped the HTTP limits (no length on text or task)."""
    with pytest.raises(ValidationError):
        Observation.decode(payload)


@pytest.mark.parametrize("deadline", [b"Infinity", b"NaN", b"-Infinity", b"1e400"])
def test_a_request_deadline_is_finite(deadline: bytes) -> None:
    """Issue 14: 'deadline_s: Infinity' on the bus ran the backends with no timeout."""
    request = ReasonerRequest(request_id="q1", observation=OBS, deadline_s=1.0,
                              options=(Option(index=0, label="continue"),))
    payload = request.encode().replace(b'"deadline_s":1.0', b'"deadline_s":' + deadline)
    assert payload != request.encode()
    with pytest.raises(ValidationError):
        ReasonerRequest.decode(payload)


def test_a_free_port_is_outside_the_range_outgoing_connections_take_theirs_from() -> None:
    """A CI run lost a test stack's service to EADDRINUSE: the port picked for it was in
    the kernel's ephemeral range, and an outgoing connection took it before the service
    bound it."""
    low, high = ephemeral_range()
    ports = [free_port() for _ in range(50)]
    assert not [p for p in ports if low <= p <= high]
    more = Ports.free(["control-robot1", "sim-robot1"])
    mine = [v for k, v in vars(more).items() if k != "more"] + [p for _, p in more.more]
    assert len(set(mine)) == 10  # a stack's ports are distinct
    assert more.of("control-robot1", "control", 1) == dict(more.more)["control-robot1"]
    assert Ports().of("control-robot2", "control", 2) == 8203  # the default: 100 apart


def test_a_spread_is_its_median_p99_and_max_or_none_without_values() -> None:
    from shared.stats import spread

    got = spread([1.0, 2.0, 3.0, 4.0, 100.0], "age")
    assert got == {"age_p50_ms": 3.0, "age_p99_ms": pytest.approx(96.16), "age_max_ms": 100.0}
    assert spread([], "tick") == {"tick_p50_ms": None, "tick_p99_ms": None, "tick_max_ms": None}
