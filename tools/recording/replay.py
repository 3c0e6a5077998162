"""``aesop replay``: a recording published on Zenoh again, with its original timing.

Each message goes out on the key it was recorded from, its payload unchanged, when
its arrival time (MCAP log time) comes round again, scaled by ``speed``: the
dashboard and ``aesop watch`` then show the recorded flight, or a live stack's
detector sees the recorded observations (``--topics observation``). The file is read
as a stream, so a recording of any length replays in constant memory; ``loop``
starts it over when it ends.

Replay publishes as whoever its session is: a Zenoh router that checks users lets
``robot-<id>`` put only its observations and its own events (``aesop up``'s ACL), and drops
the rest without a word, so a whole flight is replayed into a dashboard that is not
behind that router (docs/recordings.md).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from shared.bus import zenoh_config
from shared.settings import BusSettings

from .mcapfile import check_topics, read_messages, topic_of

Say = Callable[[str], None]


@dataclass(frozen=True)
class Replayed:
    messages: int
    bytes: int
    seconds: float
    passes: int  # complete passes through the file


def topic_filter(wanted: Sequence[str] | None) -> Callable[[str], bool]:
    """Whether a recorded key is one of the ``wanted`` topics (names as in
    :data:`~.mcapfile.MODELS`; every topic when None). Read as the recorder reads it
    (:func:`~.mcapfile.topic_of`): an event's key names its source,
    ``aesop/<robot>/event/<source>``, and is the topic ``event``."""
    names = set(check_topics(wanted))
    return lambda key: topic_of(key) in names


def due_s(log_time_ns: int, first_ns: int, speed: float) -> float:
    """Seconds after the replay's start at which a message recorded at ``log_time_ns``
    goes out (the recording's first message at 0)."""
    return max(0.0, (log_time_ns - first_ns) / 1e9 / speed)


def replay(settings: BusSettings, path: Path, *, speed: float = 1.0,
           wanted: Sequence[str] | None = None, loop: bool = False, stop: threading.Event,
           say: Say, every_s: float = 1.0, settle_s: float = 0.5,
           clock: Callable[[], float] = time.monotonic,
           wait: Callable[[float], bool] | None = None) -> Replayed:
    """Publish ``path`` until it ends (or, with ``loop``, until ``stop`` is set).
    ``settle_s``: a pause after joining, so that the subscribers the session has just
    met have been told of before the first message goes. ``clock`` and ``wait`` (True:
    stop; default ``stop.wait``) keep the schedule: a test gives its own."""
    if not speed > 0:
        raise ValueError("speed must be > 0")
    wait = wait or stop.wait
    keep = topic_filter(wanted)
    messages = sent_bytes = passes = 0
    start = clock()
    last_said = start
    session = zenoh.open(zenoh_config(settings))
    publishers: dict[str, zenoh.Publisher] = {}
    try:
        if wait(settle_s):
            return Replayed(0, 0, 0.0, 0)
        say(f"replaying {path} at {speed:g}x{' in a loop' if loop else ''}; Ctrl-C to stop")
        while not stop.is_set():
            began = clock()
            first: int | None = None
            this_pass = 0
            for record in read_messages(path):
                if not keep(record.key):
                    continue
                first = record.log_time_ns if first is None else first
                ahead = began + due_s(record.log_time_ns, first, speed) - clock()
                if ahead > 0 and wait(ahead):
                    break
                publisher = publishers.get(record.key)
                if publisher is None:
                    publisher = publishers[record.key] = session.declare_publisher(record.key)
                publisher.put(record.data)
                this_pass += 1
                sent_bytes += len(record.data)
                now = clock()
                if now - last_said >= every_s:
                    last_said = now
                    say(f"replaying: {messages + this_pass} messages, "
                        f"{(record.log_time_ns - first) / 1e9:.1f} s of the recording")
            messages += this_pass
            if stop.is_set() or this_pass == 0:
                break
            passes += 1
            if not loop:
                break
    finally:
        for publisher in publishers.values():
            publisher.undeclare()
        session.close()
    return Replayed(messages, sent_bytes, clock() - start, passes)
