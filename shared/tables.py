"""Plain-text tables for benchmark reports (``aesop bench ...``) and the demo's summary."""

from __future__ import annotations

import textwrap
from collections.abc import Mapping, Sequence
from typing import Any


def table(title: str, rows: Sequence[Mapping[str, Any]]) -> str:
    """A title, a header from the first row's keys, right-aligned columns."""
    if not rows:
        return f"{title}\n  (no rows)\n"
    header = list(rows[0])
    cells = [[cell(row.get(col)) for col in header] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) for i, h in enumerate(header)]
    lines = [title, "  " + "  ".join(h.rjust(w) for h, w in zip(header, widths, strict=True))]
    lines += ["  " + "  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True))
              for r in cells]
    return "\n".join(lines) + "\n"


def cell(value: Any) -> str:
    """None -> "-", booleans -> yes/NO, floats to 3 decimals (none from 100 up)."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "NO"
    if isinstance(value, float):
        return f"{value:.3f}" if abs(value) < 100 else f"{value:.0f}"
    return str(value)


def fitted(titles: Sequence[str], rows: Sequence[Sequence[str]], width: int = 100,
           gap: int = 2) -> str:
    """Left-aligned columns in at most ``width`` characters a line (a terminal's): each
    title wraps at its words, bottom-aligned over a rule; columns too wide together wrap
    their cells too, the widest first, so a row may take more than one line. Room left
    over widens the columns whose titles wrap most."""
    widths = _fit(titles, rows, width - gap * (len(titles) - 1))
    heads = [_wrap(title, w) for title, w in zip(titles, widths, strict=True)]
    height = max(len(h) for h in heads)
    heads = [[""] * (height - len(h)) + h for h in heads]
    lines = [_joined(list(line), widths, gap) for line in zip(*heads, strict=True)]
    lines.append(_joined(["-" * w for w in widths], widths, gap))
    for row in rows:
        cells = [_wrap(c, w) for c, w in zip(row, widths, strict=True)]
        tall = max(len(c) for c in cells)
        lines += [_joined([c[i] if i < len(c) else "" for c in cells], widths, gap)
                  for i in range(tall)]
    return "\n".join(lines)


def _fit(titles: Sequence[str], rows: Sequence[Sequence[str]], room: int) -> list[int]:
    """Each column's width: its longest cell (and title word), shrunk (the widest first, not
    below its longest word while another can give) to fit ``room``, or grown into it."""
    words = [max(len(w) for w in [*title.split(), *(w for r in rows for w in r[i].split()), ""])
             for i, title in enumerate(titles)]
    widths = [max([words[i], *(len(r[i]) for r in rows)]) for i in range(len(titles))]
    while sum(widths) > room:
        give = [i for i, w in enumerate(widths) if w > words[i]] or \
            [i for i, w in enumerate(widths) if w > 1]
        if not give:
            break
        widest = max(give, key=lambda i: widths[i])
        widths[widest] -= 1
    while sum(widths) < room:  # fewer title lines where there is room
        tall = sorted(range(len(titles)), key=lambda i: -len(_wrap(titles[i], widths[i])))
        grown = False
        for i in tall:
            lines = len(_wrap(titles[i], widths[i]))
            more = next((w for w in range(widths[i] + 1, widths[i] + room - sum(widths) + 1)
                         if len(_wrap(titles[i], w)) < lines), None)
            if lines > 1 and more is not None:
                widths[i], grown = more, True
                break
        if not grown:
            break
    return widths


def _wrap(text: str, width: int) -> list[str]:
    return textwrap.wrap(text, width, break_on_hyphens=False) or [""]


def _joined(cells: Sequence[str], widths: Sequence[int], gap: int) -> str:
    return (" " * gap).join(c.ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip()
