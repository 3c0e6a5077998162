"""``aesop watch``: the dashboard's stream as lines in a terminal.

One line per state at most every ``state_every_s`` seconds (and at every mode
change); the first flagged verdict of a run (and one whose reason changes), then the
return to nominal saying how many were flagged; every reasoner request and decision;
each event, but at most ``BURST`` of a kind per ``REPEAT_S`` per robot, the next one
shown saying how many were not; and services appearing and vanishing. Plans are left to the
dashboard. ``--robot all`` follows every robot of a fleet, each line
led by its robot (each robot's states throttled and its flags followed on their own).
:class:`Terminal` is the pure part; :func:`watch` the I/O.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, TextIO

import zenoh

from shared import topics
from shared.bus import zenoh_config
from shared.settings import BusSettings

from .feed import Update, follow

Json = dict[str, Any]
_KEEP_REQUESTS = 32
_KEEP_ROBOTS = 1024
REPEAT_S = 5.0  # events of one kind (per robot): at most BURST lines in this long
BURST = 3  # (a flight's mode changes come a few at a time; a flapping alarm, every tick)
_KEEP_KINDS = 64  # event kinds remembered per robot


@dataclass
class _Seen:
    """What one robot's lines depend on."""

    last_state: float | None = None  # received time of the last printed state
    last_mode: str | None = None
    flagged: bool = False
    run: int = 0  # flagged verdicts in the current run
    run_since: float = 0.0  # when it began
    run_reason: str | None = None  # the reason last printed
    run_top: float = -math.inf  # its highest score
    # event kind -> (when its window began, lines shown in it, events not shown since)
    events: dict[str, tuple[float, int, int]] = field(default_factory=dict)


class Terminal:
    """Turns updates into lines (or None: nothing worth a line); ``fleet``: every robot's,
    each line led by its robot."""

    def __init__(self, state_every_s: float = 1.0, *, fleet: bool = False) -> None:
        self.state_every_s = state_every_s
        self.fleet = fleet
        self._robots: OrderedDict[str, _Seen] = OrderedDict()
        self._labels: OrderedDict[str, dict[int, str]] = OrderedDict()

    def line(self, update: Update) -> str | None:
        render = {"state": self._state, "anomaly": self._anomaly, "request": self._request,
                  "decision": self._decision, "event": self._event,
                  "health": self._health}.get(update.kind)
        text = None if render is None else render(update.message, update)
        if text is None:
            return None
        clock = time.strftime("%H:%M:%S", time.localtime(update.received))
        millis = int(math.modf(update.received)[0] * 1000)
        who = ""
        if self.fleet:
            who = f"{'-' if update.kind == 'health' else topics.robot_of(update.topic):<10} "
        return f"{clock}.{millis:03d} {who}{update.kind:<8} {text}"

    def _seen(self, update: Update) -> _Seen:
        robot = topics.robot_of(update.topic)
        seen = self._robots.pop(robot, None) or _Seen()
        self._robots[robot] = seen  # the most recent last; the oldest forgotten past 1024
        while len(self._robots) > _KEEP_ROBOTS:
            self._robots.popitem(last=False)
        return seen

    def _state(self, m: Json, update: Update) -> str | None:
        seen = self._seen(update)
        due = (seen.last_state is None
               or update.received - seen.last_state >= self.state_every_s)
        if not due and m["mode"] == seen.last_mode:
            return None
        seen.last_state, seen.last_mode = update.received, m["mode"]
        x = m["x"]
        speed = math.sqrt(sum(v * v for v in x[3:6]))
        text = (f"t={m['t']:7.2f} s  {m['mode']:<15} pos=({x[0]:6.2f}, {x[1]:6.2f}, "
                f"{x[2]:6.2f}) m  |v|={speed:4.2f} m/s")
        if m.get("chosen") is not None:
            text += f"  y={m['chosen']}"
        return text

    def _anomaly(self, m: Json, update: Update) -> str | None:
        seen = self._seen(update)
        flagged, reason = bool(m["is_anomaly"]), m.get("reason")
        was, seen.flagged = seen.flagged, flagged
        tau = "none (uncalibrated)" if m["threshold"] is None else f"{m['threshold']:.3f}"
        if flagged:
            if not was:
                seen.run, seen.run_since, seen.run_top = 0, update.received, -math.inf
            seen.run += 1
            seen.run_top = max(seen.run_top, float(m["score"]))
            if was and reason == seen.run_reason:
                return None  # the same anomaly, still flagged: counted for the summary
            seen.run_reason = reason
            text = f"ANOMALY seq={m['seq']} score={m['score']:.3f} tau={tau}"
            return f"{text} ({reason})" if reason else text
        if not was:
            return None
        return (f"nominal again seq={m['seq']} score={m['score']:.3f} tau={tau}, after "
                f"{seen.run} flagged verdict(s) in {update.received - seen.run_since:.1f} s "
                f"(highest score {seen.run_top:.3f})")

    def _request(self, m: Json, _u: Update) -> str:
        self._labels[m["request_id"]] = {o["index"]: o["label"] for o in m["options"]}
        while len(self._labels) > _KEEP_REQUESTS:
            self._labels.popitem(last=False)
        options = " | ".join(f"{o['index']} {o['label']}" for o in m["options"])
        return (f"{m['request_id'][:8]} K={m['deadline_s']:.2f} s "
                f"\"{_short(m['observation']['text'], 60)}\" options: {options}")

    def _decision(self, m: Json, _u: Update) -> str:
        label = self._labels.get(m["request_id"], {}).get(m["choice"], "?")
        text = (f"{m['request_id'][:8]} y={m['choice']} {label} "
                f"(source={m['source']}, {m['latency_ms']:.0f} ms)")
        if m.get("rationale"):
            text += f" {_short(m['rationale'], 60)}"
        return text

    def _event(self, m: Json, update: Update) -> str | None:
        seen = self._seen(update)
        kind = f"{m['source']}/{m['kind']}"
        since, shown, unsaid = seen.events.pop(kind, (-math.inf, 0, 0))
        if update.received - since < REPEAT_S and shown >= BURST:
            seen.events[kind] = (since, shown, unsaid + 1)
            return None
        if update.received - since >= REPEAT_S:  # a new window; unsaid: the last one's
            seen.events[kind] = (update.received, 1, 0)
        else:  # within the window's burst (nothing unsaid in it yet)
            seen.events[kind] = (since, shown + 1, 0)
        while len(seen.events) > _KEEP_KINDS:  # the most recent last
            seen.events.pop(next(iter(seen.events)))
        text = f"[{m['severity']}] {kind}"
        if m.get("message"):
            text += f": {m['message']}"
        if unsaid:
            text += f" (and {unsaid} more like it since the last one shown)"
        return text

    def _health(self, m: Json, _u: Update) -> str:
        return f"{m['service']} {'alive' if m['alive'] else 'gone'}"


def _short(text: str, width: int) -> str:
    text = " ".join(text.split())
    return text if len(text) <= width else text[: width - 1] + "…"


async def watch(settings: BusSettings, out: TextIO, state_every_s: float = 1.0, *,
                fleet: bool = False) -> None:
    """Print the robot's stream to ``out`` until cancelled (no liveliness token of its own);
    ``fleet``: every robot's."""
    terminal = Terminal(state_every_s, fleet=fleet)

    def sink(update: Update) -> None:
        text = terminal.line(update)
        if text is not None:
            print(text, file=out, flush=True)

    with zenoh.open(zenoh_config(settings)) as session:
        await follow(session, topics.ANY_ROBOT if fleet else settings.robot, sink)
