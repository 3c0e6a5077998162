"""shared.tables.fitted: a table that keeps within a terminal's width."""

from __future__ import annotations

import pytest

from shared.tables import fitted


def test_a_table_that_fits_is_one_line_a_row_under_one_line_of_titles() -> None:
    text = fitted(["name", "ended in"], [["1-nominal", "red-box"], ["2a", "blue-box"]])
    assert text.splitlines() == ["name       ended in",
                                 "---------  --------",
                                 "1-nominal  red-box",
                                 "2a         blue-box"]


@pytest.mark.parametrize("width", [40, 60, 100])
def test_a_wide_table_wraps_its_widest_cells_and_titles_within_the_width(width: int) -> None:
    rows = [["2a-quadrotor-on-red-box", "alternative landing site (control fallback at K)",
             "0.89 / 0.01 / 1.17"], ["3", "continue (llm)", "-"]]
    titles = ["scenario", "decision (source)", "speed before / slowest waiting / after [m/s]"]
    lines = fitted(titles, rows, width).splitlines()
    assert max(len(line) for line in lines) <= width
    rule = next(i for i, line in enumerate(lines) if set(line) == {"-", " "})
    assert lines[rule].split() and len(lines[rule].split()) == 3
    body = " ".join(" ".join(lines[rule + 1:]).split())
    # nothing is lost: every character of every cell is there
    assert sorted("".join(body.split())) == sorted("".join("".join(sum(rows, [])).split()))
    if width < 60:  # no room for the longest words side by side: they break
        return
    # every word of every cell is kept, a name is not broken while another column can give
    for word in " ".join(sum(rows, [])).split():
        assert word in body.split(), word
    assert lines[rule + 1].startswith("2a-quadrotor-on-red-box")
    assert set(" ".join(lines[:rule]).split()) == set(" ".join(titles).split())


def test_room_left_over_unwraps_a_title() -> None:
    lines = fitted(["state age at the loop p50 / p99 [ms]"], [["4.8 / 19.2"]]).splitlines()
    assert lines[0] == "state age at the loop p50 / p99 [ms]"
    narrow = fitted(["state age at the loop p50 / p99 [ms]"], [["4.8 / 19.2"]], 12)
    assert narrow.splitlines()[-1] == "4.8 / 19.2" and len(narrow.splitlines()) > 3
