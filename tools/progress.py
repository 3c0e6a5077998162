"""What a long ``aesop`` command is doing, on stderr: one way for every command.

A command that runs for more than a few seconds (``aesop demo``, ``aesop detector eval``,
``aesop bench ...``, ``aesop cache import``) wraps its work in :func:`shown` and says where
it is with :func:`step` (a new step: what, and n of N where it knows), :func:`count` (items
done within the step) and :func:`say` (a line to keep). Where stderr is a terminal, one
live line (rich) shows the step, its count and the time since the command started, and
the kept lines scroll above it; elsewhere (CI logs, a file) each step is one plain line,
``aesop demo [1:05] flight 2a-quadrotor-on-red-box (2 of 4)``, counts are not printed, and
kept lines are printed as they are. Nothing of it reaches stdout, which stays the
command's tables or JSON: :func:`out` prints them while the live line is up (above it
where stdout is that terminal too; as they are into a pipe). A benchmark asks for a line
that redraws only when something changes (``ticking=False``): no thread of the display's
wakes during its timings.

The functions reach the display of the innermost :func:`shown` block of the process; with
none, :func:`step` and :func:`count` do nothing and :func:`say` prints a plain line, so
library code may call them whoever called it (a test, another command).
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TextIO

Clock = Callable[[], float]


def clock_text(seconds: float) -> str:
    """``m:ss``, or ``h:mm:ss`` from an hour on."""
    whole = max(0, int(seconds))
    hours, rest = divmod(whole, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


def step_text(label: str, n: int | None = None, total: int | None = None) -> str:
    """A step as shown: ``label (n of total)``, or what of it is known."""
    if n is None:
        return label
    return f"{label} ({n} of {total})" if total is not None else f"{label} ({n})"


def count_text(done: int, total: int | None = None, unit: str = "") -> str:
    """Items done within a step: ``245 of 1000 decisions``."""
    of = "" if total is None else f" of {total}"
    return f"{done}{of}{' ' + unit if unit else ''}"


def plain_line(title: str, elapsed_s: float, step: str) -> str:
    """A step where no live line can be drawn: one line, the time since the start first."""
    return f"{title} [{clock_text(elapsed_s)}] {step}"


def live_wanted(isatty: bool, environ: dict[str, str] | os._Environ[str]) -> bool:
    """A live line only on a terminal that can redraw one (not ``TERM=dumb``)."""
    return isatty and environ.get("TERM", "") not in ("dumb", "unknown")


class Progress:
    """The display of one command: a live line (``live``) or plain lines, on ``stream``.
    ``ticking``: the live line redraws itself (its clock and spinner) from a thread; without
    it, only when something changes (a benchmark's timings must not hold that thread)."""

    REDRAW_S = 0.25  # a count redraws the line at most this often

    def __init__(self, title: str, stream: TextIO, *, live: bool, ticking: bool = True,
                 clock: Clock = time.monotonic) -> None:
        self.title, self.stream, self.live, self.clock = title, stream, live, clock
        self.ticking = ticking
        self.started = clock()
        self.step_shown = ""  # the step as shown (none yet: the title alone)
        self._drawn = -self.REDRAW_S
        self._lock = threading.RLock()
        self._rich: Any = None  # rich.progress.Progress while the live line is up
        self._task: Any = None
        self._logging: list[tuple[logging.StreamHandler[Any], Any]] = []

    def elapsed(self) -> float:
        return self.clock() - self.started

    def step(self, label: str, n: int | None = None, total: int | None = None) -> None:
        with self._lock:
            self.step_shown = step_text(label, n, total)
            if self._rich is not None:
                self._redraw(self._describe(), at_once=True)
            else:
                self._print(plain_line(self.title, self.elapsed(), self.step_shown))

    def count(self, done: int, total: int | None = None, unit: str = "") -> None:
        """Items done in this step: on the live line only (a log gets a line per step)."""
        with self._lock:
            if self._rich is not None:
                self._redraw(self._describe(count_text(done, total, unit)), at_once=False)

    def _describe(self, counted: str = "") -> str:
        """The live line's text: the title, the step, the count within it."""
        return " · ".join(part for part in (self.title + (": " + self.step_shown
                                                          if self.step_shown else ""), counted)
                          if part)

    def _redraw(self, description: str, *, at_once: bool) -> None:
        self._rich.update(self._task, description=description)
        now = self.clock()
        if at_once or (not self.ticking and now - self._drawn >= self.REDRAW_S):
            self._drawn = now
            self._rich.refresh()

    def say(self, message: str) -> None:
        with self._lock:
            if self._rich is not None:
                self._above(message)
            else:
                self._print(message)

    def out(self, text: str, file: TextIO | None = None) -> None:
        """``text`` on stdout (or ``file``): where that is the terminal too, above the live
        line, as rich prints there; elsewhere (a pipe, a file) as it is."""
        target = sys.stdout if file is None else file
        with self._lock:
            if self._rich is not None and _isatty(target):
                self._above(text)
            else:
                print(text, file=target, flush=True)

    def _above(self, text: str) -> None:
        self._rich.console.print(text, markup=False, highlight=False, soft_wrap=True)

    def _print(self, line: str) -> None:
        print(line, file=self.stream, flush=True)

    def start(self) -> None:
        if not self.live:
            return
        from rich.console import Console
        from rich.progress import Progress as RichProgress
        from rich.progress import SpinnerColumn, TextColumn, TimeElapsedColumn

        console = Console(file=self.stream, force_terminal=True, highlight=False)
        # stderr's other writers (warnings, a print) above the line, and stdout's where it
        # is a terminal too (else it is left alone: a pipe gets what it always got)
        ours = self.stream is sys.stderr
        self._rich = RichProgress(SpinnerColumn(), TextColumn("{task.description}", markup=False),
                                  TimeElapsedColumn(), console=console, transient=True,
                                  auto_refresh=self.ticking, refresh_per_second=4,
                                  redirect_stdout=ours and _isatty(sys.stdout),
                                  redirect_stderr=ours)
        self._task = self._rich.add_task(self._describe(), total=None)
        self._rich.start()
        self._route_logging()

    def stop(self) -> None:
        with self._lock:
            for handler, stream in self._logging:
                handler.setStream(stream)
            self._logging = []
            if self._rich is not None:
                self._rich.stop()
                self._rich = None

    def _route_logging(self) -> None:
        """Log lines bound for this stream go above the live line (through rich's proxy
        of ``sys.stderr``), not across it."""
        for handler in logging.getLogger().handlers:
            if isinstance(handler, logging.StreamHandler) and \
                    handler.stream is getattr(sys.stderr, "rich_proxied_file", None):
                self._logging.append((handler, handler.stream))
                handler.setStream(sys.stderr)


def _isatty(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no such method, or closed
        return False


_shown: list[Progress] = []  # the displays of this process, the innermost last


@contextmanager
def shown(title: str, *, stream: TextIO | None = None, live: bool | None = None,
          ticking: bool = True, clock: Clock = time.monotonic) -> Iterator[Progress]:
    """Show the progress of ``title`` (``aesop demo``) until the block ends: on ``stream``
    (stderr), live where it is a terminal unless ``live`` says otherwise; ``ticking=False``
    for a benchmark (:class:`Progress`). Inside another block, that block's display goes
    on."""
    if _shown:
        yield _shown[-1]
        return
    stream = sys.stderr if stream is None else stream
    if live is None:
        live = live_wanted(_isatty(stream), os.environ)
    display = Progress(title, stream, live=live, ticking=ticking, clock=clock)
    display.start()
    _shown.append(display)
    try:
        yield display
    finally:
        _shown.pop()
        display.stop()


def step(label: str, n: int | None = None, total: int | None = None) -> None:
    """A new step of the command shown (nothing when none is)."""
    if _shown:
        _shown[-1].step(label, n, total)


def count(done: int, total: int | None = None, unit: str = "") -> None:
    """Items done within the step (on a live line only)."""
    if _shown:
        _shown[-1].count(done, total, unit)


def say(message: str) -> None:
    """A line to keep, on stderr (above the live line when one is up)."""
    if _shown:
        _shown[-1].say(message)
    else:
        print(message, file=sys.stderr, flush=True)


def out(text: str, file: TextIO | None = None) -> None:
    """``text`` on stdout, or ``file`` (the stdout of before a redirection), the live line
    taken down while it is printed."""
    if _shown:
        _shown[-1].out(text, file)
    else:
        print(text, file=sys.stdout if file is None else file, flush=True)
