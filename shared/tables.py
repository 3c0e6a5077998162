"""Plain-text tables for benchmark reports (``aesop bench ...``)."""

from __future__ import annotations

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
