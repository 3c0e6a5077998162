"""``aesop record``: the stack's Zenoh topics into an MCAP file until Ctrl-C.

A Zenoh callback only hands each sample (key, payload, arrival time) to a queue; the
calling thread writes the file (:class:`~.mcapfile.FlightWriter` is not thread-safe)
and says, once a second, what it has recorded. The session joins the bus like any
other (``AESOP_ZENOH_*``; against ``aesop up`` or compose as the read-only ``monitor``
user). It subscribes ``aesop/<robot>/**`` for the robot given, else every robot.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from shared import topics
from shared.bus import zenoh_config
from shared.settings import BusSettings

from .mcapfile import FlightWriter, check_topics, key_expr

Say = Callable[[str], None]


@dataclass(frozen=True)
class Totals:
    messages: int
    bytes: int
    seconds: float
    cpu_s: float  # the writing thread's CPU time (decoding the stamp, compressing, writing)
    skipped: int  # samples on keys of no known type


def key_exprs(robot: str | None, wanted: Sequence[str] | None) -> list[str]:
    """What to subscribe: every known topic of ``robot`` (``*``: any), or ``wanted``
    of them (names as in :data:`~.mcapfile.MODELS`)."""
    who = robot or topics.ANY_ROBOT
    return [key_expr(who, name) for name in check_topics(wanted)]


def record(settings: BusSettings, out: Path, *, robot: str | None = None,
           wanted: Sequence[str] | None = None, stop: threading.Event,
           say: Say, every_s: float = 1.0, ready: threading.Event | None = None) -> Totals:
    """Record until ``stop`` is set; the file is finished (indexed) on return. ``ready``
    is set once the subscribers are declared."""
    exprs = key_exprs(robot, wanted)
    samples: queue.SimpleQueue[tuple[str, bytes, int]] = queue.SimpleQueue()

    def on_sample(sample: zenoh.Sample) -> None:  # a Zenoh thread: hand it on, nothing else
        if sample.kind == zenoh.SampleKind.PUT:
            samples.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    writer = FlightWriter(out)
    skipped = 0
    start = time.monotonic()
    cpu_start = time.thread_time()
    last_said = start
    session = zenoh.open(zenoh_config(settings))
    subscribers = [session.declare_subscriber(expr, on_sample) for expr in exprs]
    try:
        if ready is not None:
            ready.set()
        say(f"recording {', '.join(exprs)} into {out}; Ctrl-C to stop")
        while not stop.is_set():
            try:
                key, payload, received_ns = samples.get(timeout=0.1)
            except queue.Empty:
                key = ""
            if key and not writer.add(key, payload, received_ns, _stamp_ns(payload)):
                skipped += 1
            now = time.monotonic()
            if now - last_said >= every_s:
                last_said = now
                say(f"recording: {writer.messages} messages, {writer.bytes / 1e3:.1f} kB, "
                    f"{now - start:.0f} s")
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
        session.close()
        while not samples.empty():  # what arrived before the subscribers went
            key, payload, received_ns = samples.get_nowait()
            writer.add(key, payload, received_ns, _stamp_ns(payload))
        writer.close()
    return Totals(writer.messages, writer.bytes, time.monotonic() - start,
                  time.thread_time() - cpu_start, skipped)


def _stamp_ns(payload: bytes) -> int | None:
    """When the message was made (its ``stamp``, s), for MCAP's publish time."""
    try:
        stamp = json.loads(payload).get("stamp")
    except (ValueError, AttributeError):
        return None
    return int(stamp * 1e9) if isinstance(stamp, int | float) and stamp >= 0 else None


class Background:
    """:func:`record` on a thread of its own (``aesop demo`` records each flight):
    :meth:`start` returns once it listens, :meth:`stop` once the file is finished."""

    def __init__(self, settings: BusSettings, out: Path, *, robot: str | None = None,
                 wanted: Sequence[str] | None = None) -> None:
        self.out = out
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._totals: Totals | None = None
        self._error: BaseException | None = None

        def run() -> None:
            try:
                self._totals = record(settings, out, robot=robot, wanted=wanted,
                                      stop=self._stop, say=lambda _: None,
                                      every_s=float("inf"), ready=self._ready)
            except BaseException as exc:  # handed to the caller by start/stop
                self._error = exc
                self._ready.set()

        self._thread = threading.Thread(target=run, name=f"record {out.name}", daemon=True)

    def start(self, timeout_s: float = 30.0) -> None:
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise TimeoutError(f"the recorder of {self.out} did not join Zenoh in "
                               f"{timeout_s:g} s")
        if self._error is not None:
            raise self._error

    def stop(self, timeout_s: float = 30.0) -> Totals:
        self._stop.set()
        self._thread.join(timeout_s)
        if self._error is not None:
            raise self._error
        if self._totals is None:
            raise TimeoutError(f"the recorder of {self.out} did not finish in {timeout_s:g} s")
        return self._totals
