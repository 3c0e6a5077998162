"""The questions `aesop bench reasoner --llm local` asks a local model, and how it counts
the answers (pure)."""

from __future__ import annotations

from shared.messages import DecisionSource, ReasonerDecision
from tools.bench.templates import Answer, domain_cases, hardware_cases, summarise


def test_the_hardware_cases_ask_what_the_scenarios_expect() -> None:
    cases = {c.name: c for c in hardware_cases(deadline_s=30.0)}
    assert {n: c.expected for n, c in cases.items()} == {
        "2a-quadrotor-on-red-box": 1, "2b-both-boxes-occupied": 2, "3-keyboard-on-ground": 0}
    two_a = cases["2a-quadrotor-on-red-box"].request
    assert [o.label for o in two_a.options] == ["continue", "alternative landing site",
                                                "holding zone"]
    assert "a quadrotor on the red box" in two_a.observation.text  # seen at the spot
    assert "a keyboard on the ground" in cases["3-keyboard-on-ground"].request.observation.text
    assert two_a.deadline_s == 30.0


def answer(case: str, source: DecisionSource, choice: int, expected: int) -> Answer:
    decision = ReasonerDecision(request_id=case, choice=choice, source=source,
                                latency_ms=1000.0 * (choice + 1))
    return Answer("single-json", case, decision, expected, 10, 2.0)


def test_the_summary_tells_right_unsafe_and_fallbacks_apart() -> None:
    t = summarise([answer("2a", "llm", 1, 1), answer("2a", "llm", 0, 1),
                   answer("2b", "parse_error", 1, 2), answer("3", "llm", 0, 0)])["single-json"]
    assert (t["n"], t["right"], t["continue_when_recovery_expected"]) == (4, 2, 1)
    assert (t["parse_errors"], t["timeouts"]) == (1, 0)
    assert t["tokens_per_s_p50"] == 5.0  # 10 tokens in 2 s, llm answers only
    assert t["choices"] == {"2a": [0, 1], "2b": [1], "3": [0]}
    assert t["right_by_set"] == {"hardware": "2/4"}


def test_the_synthetic_domains_ask_to_stop_for_an_anomaly_and_go_on_for_a_nominal_scene(
        ) -> None:
    cases = domain_cases(2, deadline_s=30.0)
    assert [c.domain for c in cases] == ["warehouse"] * 4 + ["vehicle"] * 4 + ["vtol"] * 4
    for case in cases:
        assert [o.label for o in case.request.options] == ["continue", "stop"]
        assert case.expected == int("-anomaly-" in case.name)
        assert case.request.observation.task and case.request.observation.text
    assert [(c.name, c.request.observation.text) for c in domain_cases(2, 30.0)] == [
        (c.name, c.request.observation.text) for c in cases]  # seeded
    t = summarise([answer(cases[0].name, "llm", 0, cases[0].expected),
                   answer(cases[3].name, "llm", 0, cases[3].expected)])["single-json"]
    assert t["right_by_set"] == {"warehouse nominal": "1/1", "warehouse anomalies": "0/1"}
    assert t["continue_when_recovery_expected"] == 1  # an anomaly let through
