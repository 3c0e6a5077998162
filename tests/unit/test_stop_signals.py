"""shared.process.stop_on: a signal sets a stop event without deadlocking the main thread.

A handler that calls ``stop.set()`` runs on the main thread between two bytecodes; when the
main thread is inside ``stop.wait(0.2)`` holding the event's lock at that moment (re-taking
it after a timeout), ``set`` waits for that lock for ever. ``aesop up`` hung so after a
SIGINT, its services left running (seen on 2026-11-29). Here the main thread holds the
lock when the signal is handled, as it does in that window."""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator

import pytest

from shared.process import stop_on


@pytest.fixture
def restore_sigterm() -> Iterator[None]:
    before = signal.getsignal(signal.SIGTERM)
    yield
    signal.signal(signal.SIGTERM, before)


def test_a_signal_while_the_main_thread_holds_the_events_lock_still_stops(
        restore_sigterm: None) -> None:
    stop = threading.Event()
    stop_on(stop, signal.SIGTERM)
    done = threading.Event()

    def unstick() -> None:  # with the old handler the main thread never comes back
        if not done.wait(10):
            os._exit(3)

    threading.Thread(target=unstick, daemon=True).start()
    with stop._cond:  # type: ignore[attr-defined]  # the window inside Event.wait
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # bytecodes: the handler runs here, the lock held
            pass
    done.set()
    assert stop.wait(5), "the signal did not set the event"
