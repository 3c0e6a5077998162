"""Fixtures shared by the suites: two real Zenoh peers on loopback (tests/zenoh_peers.py), a
real PostgreSQL server (tests/postgres.py). The run ends by saying how much disk was free at
its start and at its lowest, and during which test: the suite builds images and writes
stacks, models and PostgreSQL clusters, and a full disk fails hundreds of tests at once, far
from the cause."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest

pytest_plugins = ("tests.zenoh_peers", "tests.postgres")

_TEMP = Path(tempfile.gettempdir())
_low: dict[str, tuple[float, str]] = {}  # the least free seen: (GiB, the test's id)


def _free_gib() -> float:
    return shutil.disk_usage(_TEMP).free / 2**30


def pytest_sessionstart() -> None:
    _low["start"] = _low["least"] = (_free_gib(), "at the start")


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    # a report reaches the process that prints the summary, also from pytest-xdist's workers
    if report.when != "teardown":
        return
    free = _free_gib()
    if free < _low["least"][0]:
        _low["least"] = (free, f"after {report.nodeid}")


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    (start, _), (least, during) = _low["start"], _low["least"]
    terminalreporter.write_line(f"free disk in {_TEMP}: {start:.1f} GiB at the start, "
                                f"{least:.1f} GiB at the lowest ({during})")
