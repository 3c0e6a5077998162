"""The demo's judging and report: pure logic, plus the HTML/PNG writer.

The scenarios themselves are :mod:`tools.scenes.hardware`.

* :func:`flight_measures` — what the paper's hardware appendix describes, per
  flight: the approach altitude, the speed before the detector fires, the
  slowest while the reasoner thinks and the fastest after it answers, and the
  closest approach to the red box once the detector has fired.
* :func:`ended_in`, :func:`judge` — where a flight ended (on the simulator's truth)
  and what went wrong.
* :func:`flight_facts`, :func:`what_happened` — what was recorded of a flight, told:
  stale verdicts and when, the anomalies raised, the questions, the answers and the
  fallback, where the robot went and which decision sent it, whether the anomaly was
  ever in view and flagged.
* :func:`summary_table`, :func:`write_report` — what a person reads.
"""

from __future__ import annotations

import html
import json
import textwrap
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.control.core.outbox import BLIND
from services.control.core.regions import Tolerance
from services.control.core.scenario import Scenario
from services.sim.judge import TOLERANCE
from shared.messages import ControlState, Event, ReasonerDecision, ReasonerRequest
from shared.tables import fitted
from tools.scenes.hardware import GOAL, DemoScenario
from tools.scenes.quadrotor import TASK

GOAL_REACH_M = 0.15  # within this of the goal, and at rest, counts as landed there
AT_REST_M_S = 0.15
WIDTH = 100  # characters a line of what the demo prints on the terminal, at most


# --------------------------------------------------------------------------- judging


def ended_in(x: Sequence[float] | np.ndarray, scenario: Scenario,
             tolerance: Tolerance = TOLERANCE) -> str | None:
    """``GOAL`` when at rest on the goal, else the name of the region holding ``x``."""
    x = np.asarray(x, dtype=float)
    at_rest = float(np.linalg.norm(x[3:6])) <= AT_REST_M_S
    if at_rest and float(np.linalg.norm(x[:3] - np.asarray(scenario.goal))) <= GOAL_REACH_M:
        return GOAL
    return next((r.name for r in scenario.regions if r.contains(x, tolerance)), None)




@dataclass(frozen=True)
class FlightMeasures:
    """A flight as the paper's hardware appendix describes it (SI units, None: n/a)."""

    approach_altitude_m: float | None  # median height while 0.5..2.5 m from the goal, before it
    landed_s: float | None  # when it came to rest on the goal
    speed_before_m_s: float | None  # mean horizontal speed in the second before the detection
    speed_waiting_m_s: float | None  # the slowest from the detection to the decision
    speed_after_m_s: float | None  # the fastest in the 2 s after the decision
    closest_to_goal_m: float | None  # horizontal distance to the goal, least after detection


def flight_measures(t: Sequence[float] | np.ndarray,
                    states: Sequence[Sequence[float]] | np.ndarray,
                    modes: Sequence[str], goal: Sequence[float] | np.ndarray,
                    anomaly_at_s: float | None) -> FlightMeasures:
    """:class:`FlightMeasures` of one flight from its published states (``t`` in s)."""
    t = np.asarray(t, dtype=float)
    x = np.asarray(states, dtype=float)
    if not len(t):
        return FlightMeasures(None, None, None, None, None, None)
    goal = np.asarray(goal, dtype=float)
    reach = np.linalg.norm(x[:, :2] - goal[:2], axis=1)
    speed = np.linalg.norm(x[:, 3:5], axis=1)
    on_goal = (np.linalg.norm(x[:, :3] - goal, axis=1) <= GOAL_REACH_M) & \
        (np.linalg.norm(x[:, 3:6], axis=1) <= AT_REST_M_S)
    landed = float(t[np.argmax(on_goal)]) if on_goal.any() else None
    before_goal = t < (landed if landed is not None else np.inf)
    near = (reach > 0.5) & (reach < 2.5) & before_goal
    altitude = float(np.median(x[near, 2])) if near.any() else None

    def over(mask: np.ndarray, how=np.mean) -> float | None:
        return float(how(speed[mask])) if mask.any() else None

    if anomaly_at_s is None:
        return FlightMeasures(altitude, landed, None, None, None, None)
    pending = np.array([m == "anomaly_pending" for m in modes])
    after = t >= anomaly_at_s
    decided = after & ~pending
    decided_s = float(t[np.argmax(decided)]) if decided.any() else None
    waiting = after & (t < (decided_s if decided_s is not None else np.inf))
    return FlightMeasures(
        altitude, landed,
        over((t >= anomaly_at_s - 1.0) & (t < anomaly_at_s)), over(waiting, np.min),
        None if decided_s is None else over((t >= decided_s) & (t < decided_s + 2.0), np.max),
        float(np.min(reach[after])) if after.any() else None)


def destination(demo: DemoScenario, decision: str | None, scenario: Scenario) -> str | None:
    """Where a flight must end given the ``decision`` taken (an option label): the goal on
    "continue", the region of that label, the scenario's end when nothing was decided."""
    if decision is None:
        return demo.expected
    if decision == "continue":
        return GOAL
    return next((r.name for r in scenario.regions if r.label == decision), None)


def judge(demo: DemoScenario, *, ended: str | None, detector_alarms: int,
          anomaly_at_s: float | None, decision: str | None, violations: int,
          scenario: Scenario | None = None, facts: FlightFacts | None = None) -> list[str]:
    """What did not go as expected (empty: the scenario passed).

    In the nominal scenario the detector must never flag the scene; an anomaly the
    control loop raised because a verdict came late (fail-safe) is reported in the
    row but is no failure as long as the flight ends where it should. With ``scenario``
    (a real model, which may decide wrong) a wrong decision is no failure: the flight
    must end safely where that decision sent it (:func:`destination`); whether the
    decision was right is the row's ``decision_right``. With ``facts`` (what was recorded
    of the flight) an anomaly that raised nothing is told as it was: never in view, in view
    but never flagged, or flagged and not acted on.
    """
    problems = []
    expected = demo.expected if scenario is None else destination(demo, decision, scenario)
    if ended != expected:
        problems.append(f"ended in {ended or 'no region'}, expected {expected}")
    if demo.expected_decision is None and detector_alarms:
        problems.append(f"the detector flagged the nominal scene {detector_alarms} times")
    if demo.expected_decision is not None and anomaly_at_s is None:
        problems.append(_not_raised(facts))
    if scenario is None and demo.expected_decision is not None \
            and decision != demo.expected_decision:
        problems.append(f"decision {decision!r}, expected {demo.expected_decision!r}")
    if violations:
        problems.append(f"{violations} ticks outside the limits")
    return problems


def _not_raised(facts: FlightFacts | None) -> str:
    """Why a scenario's anomaly raised none, as far as the record tells."""
    if facts is None:
        return "the anomaly was not detected"
    if facts.in_view_s is None:
        closest = "" if facts.closest_to_anomaly_m is None else \
            f" (closest {facts.closest_to_anomaly_m:.2f} m)"
        return f"the robot never came within view of the anomaly{closest}"
    if facts.flagged_at_s is None:
        return f"the detector never flagged the anomaly in view (from {facts.in_view_s:.2f} s)"
    return (f"the detector flagged the anomaly at {facts.flagged_at_s:.2f} s but the control "
            "loop raised none")


# --------------------------------------------------------------------------- what happened


@dataclass(frozen=True)
class Asked:
    """A question the control loop put to the reasoner (at ``t_s``), and its answer."""

    t_s: float
    about: str  # the scene the detector flagged, the silent detector, or the lost vehicle
    decision: str | None = None  # the option answered (its label), None: no answer came
    source: str | None = None  # of the answer: llm, timeout, parse_error, backend_error, refused
    answered_s: float | None = None


@dataclass(frozen=True)
class FlightFacts:
    """What was recorded of one flight, on its own clock (the loop's t, s): what
    :func:`what_happened` tells and :func:`judge` names."""

    stale_verdicts: tuple[tuple[float, float | None], ...] = ()  # (t, the verdict's age, s)
    stale_states: tuple[float, ...] = ()  # each alarm of the vehicle's state going stale
    raised_s: tuple[float, ...] = ()  # each anomaly the control loop raised (its t_anom)
    asked: tuple[Asked, ...] = ()
    fallbacks: tuple[tuple[float, str], ...] = ()  # (t, the region committed to at K)
    flagged_at_s: float | None = None  # the first anomalous verdict
    flagged: int = 0  # anomalous verdicts
    in_view_s: float | None = None  # when the scenario's anomaly came into the camera's view
    closest_to_anomaly_m: float | None = None  # horizontally, over the flight
    acted_s: float | None = None  # when the decision the flight ended with was taken
    flown_m: float | None = None  # horizontally from where it was then to where it ended


def flight_facts(demo: DemoScenario, scenario: Scenario, states: Sequence[ControlState],
                 requests: Sequence[ReasonerRequest], decisions: Sequence[ReasonerDecision],
                 events: Sequence[Event], flagged_at: Sequence[float] = ()) -> FlightFacts:
    """:class:`FlightFacts` from what the demo recorded over the bus: the loop's ``states``,
    its questions and the reasoner's answers, its ``events`` and the times (the loop's t)
    of the anomalous verdicts. Messages are put on the flight's clock by their stamps: the
    first state published from then on (a tick publishes its request and its events before
    its state; a decision counts from the tick that took it)."""
    stamps = np.array([s.stamp for s in states])

    def when(stamp: float) -> float:
        if not len(states):
            return 0.0
        i = int(np.searchsorted(stamps, stamp - 1e-9, side="left"))
        return float(states[min(i, len(states) - 1)].t)

    labels = {r.index: r.label for r in scenario.regions}
    answers = {d.request_id: d for d in decisions}
    asked = []
    for q in requests:
        options = {o.index: o.label for o in q.options}
        about = ("the scene the detector flagged" if "continue" in options.values() else
                 "the vehicle's state, which had stopped arriving"
                 if q.observation.text.startswith(BLIND) else "the silent detector")
        got = answers.get(q.request_id)
        asked.append(Asked(when(q.stamp), about) if got is None else Asked(
            when(q.stamp), about, options.get(got.choice, str(got.choice)), got.source,
            when(got.stamp)))
    fallbacks = tuple((when(e.stamp), _label(labels, e.data.get("chosen")))
                      for e in events if e.kind == "fallback")
    raised: list[float] = []
    for s in states:
        if s.t_anom is not None and (not raised or abs(s.t_anom - raised[-1]) > 1e-6):
            raised.append(s.t_anom)
    in_view_s = closest = None
    x = np.array([s.x for s in states]) if len(states) else np.zeros((0, 12))
    if demo.anomalies and demo.spot is not None and len(x):
        reach = np.hypot(x[:, 0] - demo.spot[0], x[:, 1] - demo.spot[1])
        closest = float(reach.min())
        seen = reach <= demo.seen_within_m
        in_view_s = float(states[int(np.argmax(seen))].t) if seen.any() else None
    answered = [a for a in asked if a.answered_s is not None]
    acted_s = fallbacks[0][0] if fallbacks else answered[-1].answered_s if answered else None
    flown = None
    if acted_s is not None and len(x):
        i = int(np.searchsorted([s.t for s in states], acted_s, side="left"))
        there = x[min(i, len(x) - 1)]
        flown = float(np.hypot(*(x[-1, :2] - there[:2])))
    return FlightFacts(
        stale_verdicts=tuple((when(e.stamp), _float(e.data.get("age_s"))) for e in events
                             if e.kind == "verdict_stale"),
        stale_states=tuple(when(e.stamp) for e in events if e.kind == "state_stale"),
        raised_s=tuple(raised), asked=tuple(asked), fallbacks=fallbacks,
        flagged_at_s=min(flagged_at) if flagged_at else None, flagged=len(flagged_at),
        in_view_s=in_view_s, closest_to_anomaly_m=closest, acted_s=acted_s, flown_m=flown)


def what_happened(demo: DemoScenario, facts: FlightFacts, *, ended: str | None,
                  decision: str | None, source: str | None) -> str:
    """One flight told from its :class:`FlightFacts`, in order: stale verdicts or states and
    when, the anomalies the loop raised, what it asked and what came back, the fallback
    at K, where the robot went and which decision sent it there, and whether the
    scenario's anomaly was ever in view and flagged. ``decision``, ``source``: the decision
    the flight ended with (the row's)."""
    said = []
    if facts.stale_verdicts:
        said.append("the anomaly verdicts went stale " + _times(
            f"at {t:.2f} s (" + ("no verdict" if age is None else f"a verdict {age:.2f} s old")
            + ")" for t, age in facts.stale_verdicts)
            + ": the control loop counted the detector as silent, an anomaly")
    if facts.stale_states:
        said.append("the vehicle's state went stale " + _times(
            f"at {t:.2f} s" for t in facts.stale_states))
    if not facts.raised_s:
        said.append("no anomaly was raised")
    else:
        said.append("the control loop raised an anomaly at " + _times(
            f"{t:.2f} s" for t in facts.raised_s))
    for q in facts.asked:
        said.append(f"at {q.t_s:.2f} s it asked the reasoner about {q.about}: " + (
            "no answer came" if q.answered_s is None else
            f"answered {q.decision!r} (source {q.source}) at {q.answered_s:.2f} s"))
    for t, label in facts.fallbacks:
        said.append(f"at {t:.2f} s, K after the anomaly and no decision acted on, the control "
                    f"loop's fallback committed to the {label}")
    end = f"the {ended}" if ended else "no region"
    if decision is not None and facts.acted_s is not None and facts.flown_m is not None:
        said.append(f"{decision!r} ({source}) sent it on at {facts.acted_s:.2f} s: it flew "
                    f"{facts.flown_m:.1f} m from there and ended in {end}")
    elif facts.raised_s:
        said.append(f"no decision was acted on; it ended in {end}")
    else:
        said.append(f"it flew the nominal route and ended in {end}")
    if demo.anomalies:
        what = " and ".join(demo.anomalies)
        if facts.in_view_s is None:
            closest = "" if facts.closest_to_anomaly_m is None else \
                f" (closest {facts.closest_to_anomaly_m:.2f} m)"
            said.append(f"it never came within {demo.seen_within_m:g} m of {what}{closest}: "
                        "the camera never saw it, so there was nothing to detect")
        elif facts.flagged_at_s is None:
            said.append(f"{what} was in the camera's view from {facts.in_view_s:.2f} s, but "
                        "no anomalous verdict came: the detector missed it")
        else:
            said.append(f"{what} came into the camera's view at {facts.in_view_s:.2f} s; the "
                        f"detector flagged {'them' if len(demo.anomalies) > 1 else 'it'} at "
                        f"{facts.flagged_at_s:.2f} s ({facts.flagged} "
                        "anomalous verdicts)")
    elif facts.flagged_at_s is not None:
        said.append(f"the detector flagged the nominal scene {facts.flagged} times, first at "
                    f"{facts.flagged_at_s:.2f} s")
    return "; ".join(said) + "."


def _times(items: Iterable[str], shown: int = 4) -> str:
    """The first ``shown`` of ``items``, and how many more."""
    items = list(items)
    more = f" and {len(items) - shown} more times" if len(items) > shown else ""
    return ", ".join(items[:shown]) + more


def _label(labels: dict[int, str], chosen: object) -> str:
    """The label of the region index ``chosen`` (as an event's data carries it)."""
    if isinstance(chosen, int) and not isinstance(chosen, bool) and chosen in labels:
        return labels[chosen]
    return str(chosen)


def _float(value: object) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) \
        else None


def stories_text(rows: Sequence[dict[str, Any]], width: int = WIDTH) -> str:
    """Each flight that did not end as expected: why not, and what happened in it (text for
    the terminal, wrapped at ``width``, each line ending in a newline; empty when all did)."""
    told = [r for r in rows if r.get("outcome") != "ok"]
    return "".join("\n" + _fill(f"{_name(r)}: {r.get('outcome')}", width) + "\n" + (
        _fill(r["what_happened"], width, "  ") + "\n" if r.get("what_happened") else "")
        for r in told)


def _fill(text: str, width: int, indent: str = "") -> str:
    """``text`` as lines of at most ``width`` characters, the later ones indented."""
    return textwrap.fill(text, width, initial_indent=indent, subsequent_indent=indent + "  ",
                         break_on_hyphens=False)


def _name(row: dict[str, Any]) -> str:
    return f"{row['robot']} {row['name']}" if row.get("robot") else str(row["name"])


# --------------------------------------------------------------------------- output

# what the terminal shows (each table at most WIDTH characters wide): how each flight
# ended, then what it measured, then how old the state and set-points were; the HTML
# report has every column in one table, result.json every value
SUMMARY = (("name", "scenario"), ("decision_shown", "decision (source)"),
           ("as_expected", "as expected"), ("decision_latency_ms", "latency [ms]"),
           ("ended_in", "ended in"), ("constraint_violations", "violations"))
MEASURES = (("name", "scenario"), ("anomaly_at_s", "anomaly at [s]"),
            ("approach_altitude_m", "approach alt. [m]"),
            ("speeds", "speed before / slowest waiting / fastest after [m/s]"),
            ("closest_to_goal_m", "closest to red box after [m]"),
            ("time_lost_s", "time lost [s]"), ("stale_verdict_alarms", "stale alarms"))
AGES = (("name", "scenario"),
        ("state_age_ms", "state age at the loop p50 / p99 / max [ms]"),
        ("setpoint_age_ms", "set-point age at the vehicle p50 / p99 / max [ms]"))
COLUMNS = (("name", "scenario"), ("anomaly_at_s", "anomaly at [s]"), ("decision", "decision"),
           ("decision_source", "source"), ("decision_right", "right"),
           ("decision_latency_ms", "latency [ms]"), ("ended_in", "ended in"),
           ("constraint_violations", "violations"), *MEASURES[2:6], MEASURES[6], *AGES[1:],
           ("outcome", "outcome"))


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "NO"
    if isinstance(value, float):
        return f"{value:.2f}"
    if isinstance(value, list | tuple):
        return " / ".join(_cell(v) for v in value)
    return str(value)


def columns(rows: Sequence[dict[str, Any]],
            shown: tuple[tuple[str, str], ...] = COLUMNS) -> tuple[tuple[str, str], ...]:
    """A table's columns: a fleet's rows (``aesop demo --robots``) name their robot."""
    return ((("robot", "robot"),) if any("robot" in r for r in rows) else ()) + shown


def _shown(row: dict[str, Any], key: str) -> str:
    """A summary cell: the decision with its source, whether the flight went as expected
    (a wrong decision flown safely is "no, safe"), the latency in whole ms; else the row's
    value."""
    if key == "decision_shown":
        source = row.get("decision_source")
        return _cell(row.get("decision")) + ("" if source is None else f" ({source})")
    if key == "as_expected":  # a real model's wrong choice, flown safely: not as expected
        if row.get("outcome") != "ok":
            return "NO"
        return "no, safe" if row.get("decision_right") is False else "yes"
    if key == "decision_latency_ms" and isinstance(row.get(key), int | float):
        return f"{row[key]:.0f}"
    return _cell(row.get(key))


def summary_table(rows: Sequence[dict[str, Any]], shown: tuple[tuple[str, str], ...] = SUMMARY,
                  width: int = WIDTH) -> str:
    """One fixed-width text table of the scenario rows, at most ``width`` characters a
    line (a long cell wraps)."""
    cols = columns(rows, shown)
    return fitted([title for _, title in cols],
                  [[_shown(r, key) for key, _ in cols] for r in rows], width)


def summary_tables(rows: Sequence[dict[str, Any]], width: int = WIDTH) -> str:
    """The terminal's summary: how each flight ended, what it measured (the paper's
    hardware appendix), the ages of the state and the set-points; each table at most
    ``width`` characters a line."""
    return "\n\n".join(summary_table(rows, shown, width) for shown in (SUMMARY, MEASURES, AGES))


def verdict_line(result: dict[str, Any]) -> str:
    """The demo's one-line verdict. With a real model (``result["k"]``): safety, and how
    many decisions were the expected ones."""
    rows = result["scenarios"]
    if "k" not in result:
        return "all scenarios ended as expected" if result["ok"] else "SOME FAILED"
    asked = [r for r in rows if r.get("decision_right") is not None]
    right = sum(bool(r["decision_right"]) for r in asked)
    safe = ("every flight ended safely where its decision sent it" if result["ok"]
            else "SOME FLIGHTS DID NOT END SAFELY")
    return f"{safe}; {right} of {len(asked)} decisions were the expected ones"


def decisions_text(result: dict[str, Any]) -> str:
    """What the model answered in each scenario, and the K flown (text for the terminal)."""
    k = result["k"]
    lines = ["", _fill(f"K: {k['why']}", WIDTH)]
    if "control" in k:  # attached: the loop's K, which the flights had
        lines.append(_fill(f"flown: {k['control']}" + (f"; {k['later']}" if "later" in k
                                                        else ""), WIDTH))
    if "to_fly_chosen" in k:  # the command on a line of its own, to copy
        todo, command = k["to_fly_chosen"]
        lines += [_fill(f"to fly K = {k['chosen_s']:g} s (the scene with it: "
                        f"{k['scene_file']}), {todo}", WIDTH), f"  {command}"]
    for r in result["scenarios"]:
        if r.get("decision") is None:
            continue
        answer = " ".join((r.get("answer") or "(no answer from the model)").split())
        right = "right" if r.get("decision_right") else "WRONG"
        lines.append(_fill(f"{r['name']}: {r['decision']} ({right}; {r['decision_source']}, "
                           f"{_cell(r.get('decision_latency_ms'))} ms): {answer[:240]}", WIDTH))
    return "\n".join(lines)


def stories_section(rows: Sequence[dict[str, Any]]) -> str:
    """What happened in each flight, from what was recorded (HTML)."""
    items = [f"<li><b>{html.escape(_name(r))}</b> ({html.escape(str(r.get('outcome')))}): "
             f"{html.escape(r['what_happened'])}</li>" for r in rows if r.get("what_happened")]
    return "<h2>What happened</h2><ul>" + "".join(items) + "</ul>" if items else ""


def decisions_section(result: dict[str, Any]) -> str:
    """The model's answer in each scenario, and how K was chosen (HTML)."""
    k = result.get("k")
    if k is None:
        return ""
    cal = k["calibration"]
    items = []
    for r in result["scenarios"]:
        if r.get("decision") is None:
            continue
        right = "the expected one" if r.get("decision_right") else (
            "<b>wrong</b> (the scenario expects another)")
        fallback = "" if r["decision_source"] == "llm" else (
            f"; no valid answer by K: the fallback chose {html.escape(r['decision'])} "
            f"and the flight ended in {html.escape(str(r['ended_in']))}")
        items.append(
            f"<li><b>{html.escape(r['name'])}</b>: {html.escape(r['decision'])}, "
            f"{right}; {html.escape(str(r['decision_source']))}, "
            f"{_cell(r.get('decision_latency_ms'))} ms{fallback}.<pre>"
            f"{html.escape(r.get('answer') or '(no answer from the model)')}</pre></li>")
    measured = ""
    if "quantiles_s" in cal:
        quantiles = ", ".join(f"{name} {value:.2f} s" for name, value in
                              cal["quantiles_s"].items())
        measured = (f" Latency over {cal['n']} answers ({cal['n_failed']} failed): mean "
                    f"{cal['mean_s']:.2f} s, {quantiles}, max {cal['max_s']:.2f} s; the "
                    f"distribution-free bound on the {cal['quantile']:.0%} quantile at "
                    f"{cal['confidence']:.0%} confidence {cal['k_upper_s']:.2f} s.")
    attached = ""
    if "control" in k:  # aesop demo --attach --measure-k: the loop's K, and how to fly K
        attached = f"<p>Flown: {html.escape(k['control'])}" + (
            f"; {html.escape(k['later'])}" if "later" in k else "") + ".</p>"
    if "to_fly_chosen" in k:
        todo, command = k["to_fly_chosen"]
        attached += (f"<p>To fly K = {k['chosen_s']:g} s (the scene with it: "
                     f"<code>{html.escape(k['scene_file'])}</code>), {html.escape(todo)}</p>"
                     f"<pre>{html.escape(command)}</pre>")
    return (f"<h2>The model's decisions</h2><p>{html.escape(k['why'])}.{measured}</p>"
            f"{attached}<ul>" + "".join(items) + "</ul>")


def plot_flights(flights: dict[str, np.ndarray], scenario: Scenario, path: Path) -> None:
    """Top (x-y) and side (x-z) views of every flight over the regions and the goal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5))
    for ax, (i, j), title in ((axes[0], (0, 1), "top view"), (axes[1], (0, 2), "side view")):
        for region in scenario.regions:
            lo, hi = region.position_lo, region.position_hi
            color = "tab:blue" if region.kind == "landing" else "tab:orange"
            ax.add_patch(Rectangle((lo[i], lo[j]), hi[i] - lo[i], max(hi[j] - lo[j], 0.05),
                                   alpha=0.25, color=color, label=region.name))
        ax.plot(scenario.goal[i], scenario.goal[j], "s", color="tab:red", ms=12,
                label="red box (goal)")
        for name, states in flights.items():
            if len(states):
                ax.plot(states[:, i], states[:, j], lw=1.8, label=name)
                ax.plot(states[-1, i], states[-1, j], "k.", ms=8)
        lo, hi = scenario.limits.position_lo, scenario.limits.position_hi
        ax.set_xlim(lo[i], hi[i])
        ax.set_ylim(lo[j], hi[j])
        ax.set_xlabel("xyz"[i] + " [m]")
        ax.set_ylabel("xyz"[j] + " [m]")
        ax.set_title(title)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def recordings_section(rows: Sequence[dict[str, Any]]) -> str:
    """Links to each flight's MCAP file, with what recording it cost."""
    items = []
    for row in rows:
        rec = row.get("recording")
        if rec:
            link = html.escape(rec["file"], quote=True)
            items.append(
                f'<li><a href="{link}">{html.escape(rec["file"])}</a>: {rec["messages"]} '
                f'messages, {rec["file_bytes"] / 1e3:.0f} kB on disk, '
                f'{rec["messages_per_s"]:g} messages/s, {rec["bytes_per_s"] / 1e3:.1f} kB/s '
                f'of JSON, {rec.get("cpu_percent", 0):g}% of a core to write</li>')
    if not items:
        return ""
    return ("<h2>Recordings</h2><p>Each flight's Zenoh topics as MCAP (Foxglove opens them; "
            "<code>aesop replay FILE</code> flies them again into a dashboard, "
            "<code>aesop detector eval --recording FILE</code> re-scores them).</p><ul>"
            + "".join(items) + "</ul>")


def write_report(out: Path, result: dict[str, Any], flights: dict[str, np.ndarray],
                 scenario: Scenario) -> Path:
    """``out/index.html`` (summary, detector, PNG of the flights) and ``out/result.json``."""
    out.mkdir(parents=True, exist_ok=True)
    plot_flights(flights, scenario, out / "flights.png")
    (out / "result.json").write_text(json.dumps(result, indent=2, allow_nan=False))
    shown = columns(result["scenarios"])
    head = "".join(f"<th>{html.escape(title)}</th>" for _, title in shown)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(_cell(r.get(key)))}</td>" for key, _ in shown)
        + "</tr>" for r in result["scenarios"])
    cal = result.get("detector", {})
    detector = html.escape(json.dumps(cal, indent=1))
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>AESOP demo report</title>
<style>body{{font-family:sans-serif;margin:2em}} table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:4px 8px}} th{{background:#eee}}</style></head>
<body><h1>AESOP demo: the paper's quadrotor hardware scenarios, in simulation</h1>
<p>Task: {html.escape(TASK)}. Scene: {html.escape(result['scene'])}; the whole stack ran as
processes over Zenoh (vector cache, reasoner with {html.escape(result['llm'])}, control loop at
{result['rate_hz']:g} Hz, the simulated vehicle its own process: its state on the bus at
{result['state_rate_hz']:g} Hz, the set-points back). Violations and where a flight
ended are judged on the simulator's truth.</p>
<table><tr>{head}</tr>{body}</table>
<p>{html.escape(verdict_line(result))}.</p>
{stories_section(result["scenarios"])}
{decisions_section(result)}
<h2>Flights</h2><img src="flights.png" alt="flights, top and side view" width="100%">
{recordings_section(result["scenarios"])}
<h2>Fast anomaly detector</h2><pre>{detector}</pre>
</body></html>
"""
    path = out / "index.html"
    path.write_text(page, encoding="utf-8")
    return path
