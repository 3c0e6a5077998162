"""What a tick says (services/control/core/outbox.py), table by table: the request to the
reasoner for each cause, and the events of each change of mode."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest

from services.control.core import outbox
from services.control.core.aesop import ControlOutput
from services.control.core.mpc import SolveStatus
from services.control.core.regions import Region
from services.control.core.verdicts import Cause
from shared.messages import AnomalyVerdict, DetectionMatch, Mode, Observation, PairMatch

REGIONS = (Region(1, "hold", "holding zone", "hover", (0.3, -0.8, 0.8), (1.3, -0.3, 1.2)),
           Region(2, "roof", "rooftop", "landing", (0.3, 0.3, 0.0), (1.3, 0.8, 0.2)))
SCENE = Observation(robot="r1", seq=7, text="a keyboard on the ground")
KEYBOARD = DetectionMatch(detection="a keyboard on the ground", nearest="a drill on the ground",
                          similarity=0.61)
PAIR = PairMatch(detections=("a person", "a forklift"), nearest=("a person", "a shelf"),
                 similarity=0.41)


def verdict(seq: int = 7, anomaly: bool = True) -> AnomalyVerdict:
    return AnomalyVerdict(robot="r1", seq=seq, score=0.4, threshold=0.7, is_anomaly=anomaly,
                          k=5, model="m", cache="c", cache_version=1, latency_ms=3.0,
                          detections=(KEYBOARD,), pair=PAIR)


class Asked(NamedTuple):
    cause: Cause | None
    verdict: AnomalyVerdict | None
    observation: Observation | None
    # what the reasoner sees
    seq: int
    text_starts: str
    text_has: str
    labels: tuple[str, ...]
    unusual: bool  # the verdict's detections and pair are quoted


ASKED = {
    "a flagged scene is asked about as it is": Asked(
        Cause.ANOMALY, verdict(), SCENE, 7, "a keyboard", "", ("continue", "holding zone",
                                                                "rooftop"), True),
    "a flagged scene whose text never arrived": Asked(
        Cause.ANOMALY, verdict(seq=9), None, 9, "the anomaly detector flagged", "",
        ("continue", "holding zone", "rooftop"), True),
    "a silent detector: told so, continue not offered": Asked(
        Cause.SILENCE, verdict(seq=5, anomaly=False), SCENE, 7, outbox.SILENT[:30],
        "the last observation:\na keyboard", ("holding zone", "rooftop"), False),
    "a silent detector and no scene at all": Asked(
        Cause.SILENCE, None, None, 0, outbox.SILENT[:30], "", ("holding zone", "rooftop"),
        False),
    "a blind vehicle: told so, even with a flagged verdict": Asked(
        Cause.VEHICLE, verdict(), SCENE, 7, outbox.BLIND[:30], "a keyboard",
        ("holding zone", "rooftop"), False),
}


@pytest.mark.parametrize("row", ASKED.values(), ids=ASKED.keys())
def test_the_request_says_what_the_reasoner_may_know_and_choose(row: Asked) -> None:
    req = outbox.request(robot="r1", request_id="abc", cause=row.cause, verdict=row.verdict,
                         observation=row.observation, regions=REGIONS, offered=(1, 2),
                         deadline_s=1.5)
    assert req.request_id == "abc" and req.deadline_s == 1.5 and req.robot == "r1"
    assert req.observation.seq == row.seq
    assert req.observation.text.startswith(row.text_starts)
    assert row.text_has in req.observation.text
    assert tuple(o.label for o in req.options) == row.labels
    assert (req.unusual, req.unusual_pair) == (((KEYBOARD,), PAIR) if row.unusual else ((), None))


def test_an_option_says_where_the_region_is() -> None:
    (land,) = outbox.options_for(REGIONS, (2,), continue_=False)
    assert (land.index, land.description) == (2, "land at roof (0.8, 0.6, 0.1) m")


def output(mode: Mode, *, fallback: bool = False, events: tuple[str, ...] = ()
           ) -> ControlOutput:
    return ControlOutput(u=np.zeros(3), mode=mode, status=SolveStatus.SOLVED, plan=None,
                         active_regions=(1, 2), t_anom=None, chosen=2 if fallback else None,
                         events=events, fallback=fallback)


class Said(NamedTuple):
    before: Mode
    output: ControlOutput
    kinds: tuple[str, ...]
    severity: str | None


SAID = {
    "same mode: the controller's notes as they are": Said(
        Mode.PENDING, output(Mode.PENDING, events=("held one tick",)), ("controller",), "info"),
    "same mode, nothing said": Said(Mode.NOMINAL, output(Mode.NOMINAL), (), None),
    "an anomaly: pending is a warning": Said(
        Mode.NOMINAL, output(Mode.PENDING), ("mode_change",), "warning"),
    "back to nominal: info": Said(Mode.PENDING, output(Mode.NOMINAL), ("mode_change",), "info"),
    "recovering on a decision: a warning": Said(
        Mode.PENDING, output(Mode.RECOVERING), ("mode_change",), "warning"),
    "recovering without one: the fallback alarm": Said(
        Mode.PENDING, output(Mode.RECOVERING, fallback=True, events=("no decision by K",)),
        ("fallback",), "alarm"),
}


@pytest.mark.parametrize("row", SAID.values(), ids=SAID.keys())
def test_a_change_of_mode_is_one_event_naming_both_modes(row: Said) -> None:
    events = outbox.mode_events("r1", row.before, row.output, "req-1")
    assert tuple(e.kind for e in events) == row.kinds
    assert all(e.severity == row.severity and e.source == "control" for e in events)
    if row.before is not row.output.mode:
        (e,) = events
        assert e.data == {"from": row.before.value, "to": row.output.mode.value,
                          "chosen": row.output.chosen, "fallback": row.output.fallback,
                          "request_id": "req-1"}
        assert e.message == ("; ".join(row.output.events)
                             or f"{row.before.value} -> {row.output.mode.value}")


def test_the_state_is_rounded_and_a_missing_plan_is_no_snapshot() -> None:
    state = outbox.control_state(robot="r1", t=0.25, x=np.arange(12.0), output=output(
        Mode.NOMINAL), t_anom=None, state_age_s=0.0123456789)
    assert state.state_age_s == 0.012346 and state.x[3] == 3.0 and state.mode == "nominal"
    assert outbox.plan_snapshot("r1", 0.25, None) is None
