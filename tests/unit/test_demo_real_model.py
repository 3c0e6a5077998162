"""``aesop demo --llm local``'s pure parts: K from the served model's calibration, kept only
when the scene can keep it, and a flight with a real model judged on safety, its decision's
rightness reported beside it (issue 27)."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.control.core.scenario import load_scenario
from tools.demo.k import (
    QUERIES,
    choose_k,
    control_k,
    how_to_fly,
    k_record,
    scene_with_k,
    tree_at_start,
)
from tools.demo.report import decisions_text, destination, judge, verdict_line
from tools.scenes.hardware import GOAL, SCENARIOS
from tools.stack.up import hardware_scenario

SCENE = load_scenario("hardware")
BY_NAME = {s.name: s for s in SCENARIOS}


def calibration(quantile: float | None) -> dict:
    return {"n": QUERIES, "n_failed": 0, "k_s": quantile,
            "k_upper_s": None if quantile is None else quantile * 2}


def test_the_calibrations_quantile_rounded_up_to_a_tick_is_flown_when_the_tree_can_wait(
        ) -> None:
    assert QUERIES == 60  # 59 bound the 95 % quantile at 95 % confidence: the slowest of 60
    for bound, flown in ((2.01, 2.05), (4.9, 4.9), (5.96, 6.0)):
        choice = choose_k(SCENE, calibration(bound))
        assert choice.k_s == pytest.approx(flown) and choice.calibrated
        assert f"K = {flown:g} s" in choice.why


@pytest.mark.parametrize(("bound", "why"), [
    (12.0, "not below T"),  # longer than the horizon
    (7.5, "no tree of recovery plans is feasible from the start"),  # fits, but cannot wait
    (None, "no bound"),  # too many queries failed (the report holds no quantile)
])
def test_a_k_the_scene_cannot_keep_leaves_the_scenes_own_and_says_why(
        bound: float | None, why: str) -> None:
    choice = choose_k(SCENE, calibration(bound))
    assert choice.k_s == SCENE.consensus_s and not choice.calibrated
    assert why in choice.why and f"flying the scene's K = {SCENE.consensus_s:g} s" in choice.why


def test_the_scene_with_k_loads_as_the_same_scene_but_for_k(tmp_path: Path) -> None:
    path = scene_with_k(hardware_scenario(), 4.9, tmp_path / "scene.yaml")
    scene = load_scenario(path)
    assert scene.consensus_s == 4.9 and scene.consensus == 98
    assert (scene.regions, scene.goal, scene.dt, scene.horizon_s) == (
        SCENE.regions, SCENE.goal, SCENE.dt, SCENE.horizon_s)
    assert tree_at_start(SCENE) is None


def test_the_record_keeps_what_was_measured_chosen_and_why() -> None:
    choice = choose_k(SCENE, calibration(4.9))
    record = k_record(choice)
    assert record == {"flown_s": 4.9, "chosen_s": 4.9, "scene_s": SCENE.consensus_s,
                      "measured_s": 4.9, "why": choice.why,
                      "calibration": calibration(4.9)}
    kept = k_record(choose_k(SCENE, calibration(7.5)))  # measured, not kept: the scene's
    assert (kept["chosen_s"], kept["measured_s"]) == (SCENE.consensus_s, 7.5)


def test_controls_k_is_read_from_the_scene_it_names(tmp_path: Path) -> None:
    """Control's GET /v1/state names its scene, not its K: the hardware scene's is its K,
    the one scene_with_k wrote carries its K in its name, any other's is not known."""
    k_s, why = control_k(SCENE.name, SCENE)
    assert k_s == SCENE.consensus_s and "not its K" in why and "the scene's" in why
    for k in (4.9, 6.65, 0.35):
        written = load_scenario(scene_with_k(hardware_scenario(), k, tmp_path / f"{k}.yaml"))
        k_s, why = control_k(written.name, SCENE)
        assert k_s == written.consensus_s == k and f"K = {k:g} s" in why
    for other in ("paper-quadrotor", f"{SCENE.name}-kx", f"{SCENE.name}-k40", f"{SCENE.name}-knan"):
        k_s, why = control_k(other, SCENE)
        assert k_s == SCENE.consensus_s and "does not report its K" in why, other


def test_a_wrong_decision_is_no_failure_when_the_flight_ends_where_it_sent_it() -> None:
    red = BY_NAME["2a-quadrotor-on-red-box"]
    assert destination(red, "holding zone", SCENE) == "holding-zone"
    assert destination(red, "continue", SCENE) == GOAL
    assert destination(red, None, SCENE) == "blue-box"
    wrong = {"detector_alarms": 3, "anomaly_at_s": 1.1, "decision": "holding zone",
             "violations": 0}
    assert judge(red, ended="holding-zone", scenario=SCENE, **wrong) == []
    assert judge(red, ended="holding-zone", **wrong) == [  # the fake LLM's demo: a failure
        "ended in holding-zone, expected blue-box",
        "decision 'holding zone', expected 'alternative landing site'"]
    assert judge(red, ended="blue-box", scenario=SCENE, **wrong) == [
        "ended in blue-box, expected holding-zone"]  # not where its decision sent it
    assert judge(red, ended="holding-zone", scenario=SCENE,
                 **{**wrong, "violations": 2}) == ["2 ticks outside the limits"]


def test_the_verdict_counts_the_right_decisions_and_the_text_quotes_each_answer() -> None:
    rows = [{"name": "1-nominal", "decision": None, "decision_right": None},
            {"name": "2a-quadrotor-on-red-box", "decision": "holding zone",
             "decision_right": False, "decision_source": "llm", "decision_latency_ms": 2710.0,
             "answer": '{"reasoning": "the box\nis taken", "answer": "holding zone"}'},
            {"name": "2b-both-boxes-occupied", "decision": "holding zone",
             "decision_right": True, "decision_source": "parse_error",
             "decision_latency_ms": 3100.0, "answer": ""}]
    result = {"ok": True, "scenarios": rows, "k": {"why": "K = 4.9 s: measured"}}
    assert verdict_line(result) == ("every flight ended safely where its decision sent it; "
                                    "1 of 2 decisions were the expected ones")
    text = decisions_text(result)
    assert "K = 4.9 s: measured" in text and "1-nominal" not in text
    assert "2a-quadrotor-on-red-box: holding zone (WRONG; llm, 2710.00 ms)" in text
    assert '"answer": "holding zone"' in text and "the box is taken" in text
    assert "(no answer from the model)" in text
    assert verdict_line({"ok": False, "scenarios": rows}) == "SOME FAILED"


def test_an_attached_stack_is_told_the_k_it_flew_and_how_to_fly_the_one_chosen(
        tmp_path: Path) -> None:
    """aesop demo --attach --measure-k: the record says what was chosen and why, the K the
    loop flew (and that later answers were its fallback), and the command to fly the K
    chosen, on a line of its own; the rest fits in 100 columns."""
    import shlex

    from tools.demo.report import decisions_section

    path = tmp_path / ("a-long-folder-name-" * 4) / "scene-with-k.yaml"
    todo, command = how_to_fly(path, compose=False)
    assert shlex.split(command) == ["aesop", "up", "--scenario", str(path)]
    assert "the options it ran with" in todo
    choice = choose_k(SCENE, calibration(5.96))
    k_s, why = control_k(SCENE.name, SCENE)
    k = k_record(choice) | {"flown_s": k_s, "control": why, "later": "answers later than "
                            f"{k_s:g} s end as the control loop's fallback",
                            "scene_file": str(path),
                            "to_fly_chosen": list(how_to_fly(path, compose=True))}
    rows = [{"name": "2a-quadrotor-on-red-box", "decision": "alternative landing site",
             "decision_right": True, "decision_source": "control fallback at K",
             "decision_latency_ms": None, "answer": None, "ended_in": "blue-box"}]
    text = decisions_text({"ok": True, "scenarios": rows, "k": k})
    lines = text.splitlines()
    (shown,) = [line for line in lines if "docker compose" in line]
    assert shown == "  " + k["to_fly_chosen"][1]
    assert max(len(line) for line in lines if line != shown) <= 100
    words = " ".join(text.split())
    assert f"K: {choice.why}" in words and f"flown: {why}; answers later than 4.3 s" in words
    assert "to fly K = 6 s" in words and "control fallback at K" in words
    page = decisions_section({"ok": True, "scenarios": rows, "k": k})
    assert "Flown: control flies the scene" in page and "AESOP_SCENE_FILE=" in page


def test_a_flight_lasts_until_a_late_anomalys_t_has_come_due() -> None:
    from shared.messages import ControlState
    from tools.demo.flights import FLIGHT_S, Recorder, flight_end

    def at(t: float, t_anom: float | None) -> ControlState:
        return ControlState(t=t, x=(0.0,) * 12, u=(0.0,) * 3, mode="nominal", t_anom=t_anom)

    rec = Recorder()
    assert flight_end(rec, SCENE) == FLIGHT_S
    rec.states = [at(1.0, None), at(7.6, 7.6)]  # the paper's timing: judged at 22 s
    assert flight_end(rec, SCENE) == FLIGHT_S
    rec.states.append(at(15.0, 14.0))  # a late one: its T (10 s) and 3 s to settle
    assert flight_end(rec, SCENE) == pytest.approx(27.0)
    rec.states.append(at(40.0, 39.0))  # never longer than twice the flight
    assert flight_end(rec, SCENE) == 2 * FLIGHT_S


def test_the_summary_does_not_call_a_wrong_decision_as_expected() -> None:
    # aesop demo --attach --measure-k against compose's SmolLM2: 2a "holding zone (llm)",
    # "as expected: yes" in the table, and "2a: holding zone (WRONG ...)" below it
    from tools.demo.report import summary_table

    rows = [{"name": "1-nominal", "decision": None, "decision_right": None, "outcome": "ok"},
            {"name": "2a", "decision": "holding zone", "decision_right": False,
             "decision_source": "llm", "outcome": "ok"},
            {"name": "2b", "decision": "continue", "decision_right": True,
             "decision_source": "llm", "outcome": "ok"},
            {"name": "3", "decision": "continue", "decision_right": True,
             "decision_source": "llm", "outcome": "ended in blue-box"}]
    lines = summary_table(rows).splitlines()[2:]
    said = {line.split()[0]: line for line in lines}
    assert " yes " in said["1-nominal"] and " yes " in said["2b"]
    assert "no, safe" in said["2a"] and " yes " not in said["2a"]
    assert " NO " in said["3"] + " "
