"""How the control loop reads the fast detector: the fail-safe policy as a table, and a
verdict's age taken from the observation it answers."""

from __future__ import annotations

import pytest

from services.control.core.verdicts import Cause, Directive, Sightings, directive, verdict_age

A, S = Cause.ANOMALY, Cause.SILENCE

# (fresh, flagged, pending, silence_asked, decision) -> what the controller is handed
POLICY = [
    # a fresh detector: its flag and the reasoner's answer pass through
    ((True, False, None, False, None), Directive(False, None)),
    ((True, True, None, False, None), Directive(True, None, A)),
    ((True, False, A, False, 0), Directive(False, 0)),  # continue, detector watching
    ((True, False, A, False, 2), Directive(False, 2)),
    ((True, True, A, False, None), Directive(True, None, A)),  # (ignored while pending)
    # silence while nominal: ask once per silent spell, about the silence
    ((False, False, None, False, None), Directive(True, None, S)),
    ((False, False, None, True, None), Directive(False, None)),
    ((False, True, None, False, None), Directive(True, None, S)),  # a stale flag is silence
    # silence while an answer is awaited: "continue" is refused, a region is taken
    ((False, False, S, True, 0), Directive(False, None, refused_continue=True)),
    ((False, False, S, True, 1), Directive(False, 1)),
    ((False, False, A, False, 0), Directive(False, None, refused_continue=True)),
    ((False, False, A, False, 2), Directive(False, 2)),
    ((False, False, S, True, None), Directive(False, None)),  # waits; fallback at K
    # the detector is back: the silent spell's episode ends, the scene judged afresh
    ((True, False, S, True, None), Directive(False, 0, ended_silence=True)),
    ((True, True, S, True, None), Directive(True, 0, A, ended_silence=True)),
    ((True, False, S, True, 0), Directive(False, 0, ended_silence=True)),
    ((True, False, S, True, 2), Directive(False, 2)),  # the reasoner's region stands
]


@pytest.mark.parametrize(("given", "expected"), POLICY,
                         ids=[f"fresh={g[0]}-flag={g[1]}-pending={g[2]}-asked={g[3]}-y={g[4]}"
                              for g, _ in POLICY])
def test_the_fail_safe_policy(given, expected):
    fresh, flagged, pending, asked, decision = given
    assert directive(fresh=fresh, flagged=flagged, pending=pending, silence_asked=asked,
                     decision=decision) == expected


def test_a_verdict_is_as_old_as_the_observation_it_answers():
    sightings = Sightings()
    for seq in range(5):
        sightings.record(seq, 100.0 + seq * 0.1)
    sightings.record(4, 500.0)  # a repeat does not make an observation new
    assert verdict_age(sightings, 4, arrived_at=101.0, now=101.0) == pytest.approx(0.6)
    # the verdict for seq 1 arrives now, but answers what was seen at 100.1
    assert verdict_age(sightings, 1, arrived_at=101.0, now=101.0) == pytest.approx(0.9)
    # an observation this tick never saw: the newest earlier one seen stands in
    assert verdict_age(sightings, 7, arrived_at=101.0, now=101.0) == pytest.approx(0.6)
    assert verdict_age(sightings, -1, arrived_at=101.0, now=101.0) is None  # older than all


def test_without_observations_a_verdict_is_as_old_as_its_arrival():
    assert verdict_age(Sightings(), 42, arrived_at=100.0, now=100.3) == pytest.approx(0.3)


def test_sightings_forget_the_oldest():
    sightings = Sightings(size=3)
    for seq in range(10):
        sightings.record(seq, float(seq))
    assert sightings.seen_at(6) is None and sightings.seen_at(9) == 9.0


def test_a_count_that_starts_again_is_a_restart():
    sightings = Sightings()
    for seq in range(100, 110):
        sightings.record(seq, float(seq))
    sightings.record(1, 500.0)  # the publisher restarted: what came before is forgotten
    assert sightings.seen_at(1) == 500.0 and sightings.seen_at(105) == 500.0
    sightings.record(2, 501.0)
    assert sightings.seen_at(2) == 501.0 and sightings.seen_at(0) is None
