"""tools.progress: what a long command shows on stderr, live on a terminal, a line a step in
a log, and nothing of it on stdout."""

from __future__ import annotations

import io
import logging
import os
import pty
import re
import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from tools import progress
from tools.progress import clock_text, count_text, live_wanted, plain_line, step_text

ROOT = Path(__file__).resolve().parents[2]
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\r")


def plain(text: str) -> str:
    """What a terminal shows of ``text``, roughly: each drawing on a line of its own."""
    return "\n".join(line.strip() for line in ANSI.sub("\n", text).splitlines())


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_the_texts() -> None:
    assert clock_text(0) == "0:00" and clock_text(65.9) == "1:05"
    assert clock_text(3 * 3600 + 61) == "3:01:01"
    assert step_text("flight 2a", 2, 4) == "flight 2a (2 of 4)"
    assert step_text("flight 2a", 2) == "flight 2a (2)" and step_text("loading") == "loading"
    assert count_text(245, 1000, "decisions") == "245 of 1000 decisions"
    assert count_text(7) == "7"
    assert plain_line("aesop demo", 65, "flight 2a (2 of 4)") == \
        "aesop demo [1:05] flight 2a (2 of 4)"


@pytest.mark.parametrize(("isatty", "term", "live"), [
    (True, "xterm-256color", True), (True, "dumb", False), (False, "xterm", False),
    (True, "", True)])
def test_a_live_line_only_on_a_terminal_that_redraws(isatty: bool, term: str,
                                                      live: bool) -> None:
    assert live_wanted(isatty, {"TERM": term}) is live


def test_a_log_gets_a_line_a_step_and_the_kept_lines_not_the_counts(
        capsys: pytest.CaptureFixture[str]) -> None:
    stream, clock = io.StringIO(), Clock()
    with progress.shown("aesop bench reasoner", stream=stream, live=False, clock=clock):
        progress.step("single backend", 1, 2)
        for n in range(1, 1001):
            progress.count(n, 1000, "decisions")
        progress.say("  p99 412 ms")
        clock.now += 65
        progress.step("hedged", 2, 2)
        progress.out("the table")
    assert stream.getvalue().splitlines() == [
        "aesop bench reasoner [0:00] single backend (1 of 2)", "  p99 412 ms",
        "aesop bench reasoner [1:05] hedged (2 of 2)"]
    assert capsys.readouterr().out == "the table\n"


def test_a_terminal_gets_one_live_line_with_the_step_its_count_and_the_time(
        capsys: pytest.CaptureFixture[str]) -> None:
    stream = io.StringIO()
    with progress.shown("aesop demo", stream=stream, live=True):
        progress.count(3, 10, "texts")  # on the line at its next redraw (its clock)
        progress.step("flight 2a-quadrotor-on-red-box [hover]", 2, 4)  # drawn at once
        progress.say("1-nominal: ok")
        progress.out("scenario  ended in")  # the table: stdout, the line taken down first
        progress.step("writing the report")
    shown = plain(stream.getvalue())
    assert "aesop demo: flight 2a-quadrotor-on-red-box [hover] (2 of 4)" \
        in shown  # no markup read into the brackets
    assert "aesop demo: writing the report" in shown and "1-nominal: ok" in shown
    assert re.search(r"\d+:\d\d:\d\d", shown)  # the time since the start
    assert stream.getvalue().endswith("\x1b[2K")  # the live line is gone at the end
    captured = capsys.readouterr()
    assert captured.out == "scenario  ended in\n"  # stdout: only what the command prints


def test_a_benchmarks_line_redraws_only_when_it_changes_and_holds_no_thread() -> None:
    stream, clock = io.StringIO(), Clock()
    before = set(threading.enumerate())
    with progress.shown("aesop bench mpc", stream=stream, live=True, ticking=False,
                        clock=clock):
        assert set(threading.enumerate()) == before  # nothing wakes during the timings
        progress.step("N = 200", 1, 2)
        for n in range(1, 101):  # all at once: drawn at most every REDRAW_S
            progress.count(n, 100, "ticks")
        clock.now += 1.0
        progress.count(100, 100, "ticks")
        progress.step("N = 400", 2, 2)
    shown = plain(stream.getvalue())
    assert "aesop bench mpc: N = 200 (1 of 2)" in shown and "(2 of 2)" in shown
    assert shown.count("of 100 ticks") == 1 and "100 of 100 ticks" in shown


def test_log_lines_go_above_the_live_line_and_the_handler_is_given_back() -> None:
    handler = logging.StreamHandler(sys.stderr)
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        with progress.shown("aesop bench detector", live=True):
            assert handler.stream is sys.stderr  # rich's proxy, which prints above the line
            assert getattr(sys.stderr, "rich_proxied_file", None) is not None
        assert getattr(handler.stream, "rich_proxied_file", None) is None
        assert handler.stream is sys.stderr
    finally:
        root.removeHandler(handler)


def test_without_a_display_steps_are_silent_and_kept_lines_go_to_stderr(
        capsys: pytest.CaptureFixture[str]) -> None:
    progress.step("flight 1", 1, 4)
    progress.count(1, 2)
    progress.say("kept")
    progress.out("table")
    assert capsys.readouterr() == ("table\n", "kept\n")


def test_an_inner_block_goes_on_with_the_outer_display() -> None:
    stream = io.StringIO()
    with progress.shown("aesop demo", stream=stream, live=False) as outer, \
            progress.shown("aesop other") as inner:
        assert inner is outer
        progress.step("inner step")
    assert stream.getvalue() == "aesop demo [0:00] inner step\n"


@pytest.fixture
def terminal() -> Iterator[tuple[int, int]]:
    main, side = pty.openpty()
    yield main, side
    os.close(main)


def test_a_command_on_a_real_terminal_draws_the_line_and_leaves_stdout_alone(
        terminal: tuple[int, int]) -> None:
    """stderr a pseudo-terminal, stdout a pipe: the live line on the one, the table on the
    other, as ``aesop demo | tee`` in a terminal."""
    main, side = terminal
    script = textwrap.dedent("""
        from tools import progress
        with progress.shown("aesop demo"):
            progress.step("flight 2a", 2, 4)
            progress.say("  2a: ok")
            progress.out("scenario  ended in")
        print("2a        blue-box")
    """)
    chunks: list[bytes] = []  # read all along: a full terminal would stop the command
    reader = threading.Thread(target=lambda: read_all(main, chunks), daemon=True)
    reader.start()
    proc = subprocess.run([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=side,
                          stdin=subprocess.DEVNULL, cwd=ROOT, env={**os.environ, "TERM": "xterm"},
                          timeout=60, text=True)
    os.close(side)
    reader.join(30)
    drawn = b"".join(chunks)
    assert proc.returncode == 0
    assert proc.stdout == "scenario  ended in\n2a        blue-box\n"
    text = drawn.decode()
    assert "\x1b[2K" in text and "aesop demo: flight 2a (2 of 4)" in plain(text)
    assert "2a: ok" in plain(text)


def test_a_table_on_the_same_terminal_is_printed_above_the_line_not_across_it(
        terminal: tuple[int, int]) -> None:
    """stdout and stderr both the terminal, as a plain ``aesop demo``: the table (and a
    stray print) scroll above the live line, whole."""
    main, side = terminal
    script = textwrap.dedent("""
        from tools import progress
        with progress.shown("aesop bench loop", ticking=False):
            progress.step("10 Hz", 1, 2)
            print("a stray print")
            progress.out("rate  jitter p50")
            progress.step("20 Hz", 2, 2)
        print("after")
    """)
    drawn = run_on(main, side, script)
    lines = [line for line in plain(drawn).splitlines() if line.strip()]
    assert "a stray print" in lines and "rate  jitter p50" in lines and lines[-1] == "after"
    assert any(line.startswith("aesop bench loop: 20 Hz (2 of 2)") for line in lines)


def run_on(main: int, side: int, script: str) -> str:
    """``script`` with stdin, stdout and stderr the terminal ``side``: what it drew."""
    chunks: list[bytes] = []
    reader = threading.Thread(target=lambda: read_all(main, chunks), daemon=True)
    reader.start()
    proc = subprocess.run([sys.executable, "-c", script], stdin=subprocess.DEVNULL,
                          stdout=side, stderr=side, cwd=ROOT, timeout=60,
                          env={**os.environ, "TERM": "xterm"})
    os.close(side)
    reader.join(30)
    assert proc.returncode == 0
    return b"".join(chunks).decode()


def read_all(fd: int, chunks: list[bytes]) -> None:
    while True:
        try:
            chunk = os.read(fd, 65536)
        except OSError:  # the other end closed
            return
        if not chunk:
            return
        chunks.append(chunk)


def test_a_command_in_a_log_prints_a_plain_line_a_step() -> None:
    script = textwrap.dedent("""
        from tools import progress
        with progress.shown("aesop demo"):
            for n in (1, 2):
                progress.step(f"flight {n}", n, 2)
                progress.count(5, 10)
        print("table")
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          stdin=subprocess.DEVNULL, cwd=ROOT, timeout=60,
                          env={**os.environ, "TERM": "xterm"})
    assert proc.returncode == 0 and proc.stdout == "table\n"
    lines = proc.stderr.splitlines()
    assert len(lines) == 2, proc.stderr  # the counts: none
    for n, line in enumerate(lines, 1):
        assert re.fullmatch(rf"aesop demo \[\d+:\d\d\] flight {n} \({n} of 2\)", line), line
