"""shared.realtime: a favoured process gets its share against other sessions too (issue 46).

Where the kernel groups processes by session (autogroups), a nice value only ranks a
process's threads inside its session; ``aesop up`` starts each service in a session of its
own, so a favoured service must also give its session's autogroup the nice value. These run
in child processes: favouring this test's own process would favour pytest's session."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from shared.realtime import AUTOGROUP

ROOT = Path(__file__).resolve().parents[2]
PROBE = ("import os\n"
         "from tests.unit.test_realtime import _own_autogroup_nice\n"
         "from shared.realtime import favoured\n"
         "print(favoured(), os.getpriority(os.PRIO_PROCESS, 0), _own_autogroup_nice())\n")


def _favoured_in_child(*, own_session: bool) -> tuple[str, str, str]:
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT,
                         capture_output=True, text=True, check=True, timeout=60,
                         start_new_session=own_session).stdout.split()
    return out[0], out[1], out[2]


def _own_autogroup_nice() -> str | None:
    """This process's autogroup nice value; None where there is none to read: no autogroups
    in this kernel, or a process in the boot session's autogroup, whose file is empty (PID 1
    and whatever it starts without a new session, as a CI runner may)."""
    group = Path(AUTOGROUP)
    fields = group.read_text().split() if group.exists() else []
    return fields[-1] if fields else None


def test_an_autogroup_file_with_nothing_in_it_reads_as_no_autogroup(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    empty = tmp_path / "autogroup"
    empty.write_text("")
    monkeypatch.setattr(sys.modules[__name__], "AUTOGROUP", str(empty))
    assert _own_autogroup_nice() is None


def test_a_session_leader_favours_its_autogroup_as_well_as_its_threads() -> None:
    favoured, nice, group = _favoured_in_child(own_session=True)
    if favoured == "False":  # no CAP_SYS_NICE: nothing may change
        assert nice == str(os.getpriority(os.PRIO_PROCESS, 0))
        return
    assert nice == "-10"
    if _own_autogroup_nice() is not None:  # the kernel groups by session
        assert group == "-10"


def test_a_process_in_another_session_leaves_that_session_as_it_is() -> None:
    before = _own_autogroup_nice()
    favoured, _, group = _favoured_in_child(own_session=False)
    assert group == str(before)
    assert _own_autogroup_nice() == before
    assert favoured in ("True", "False")
