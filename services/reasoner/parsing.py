"""Strict parsing of the slow reasoner's text into a choice y in the offered set.

The prompt (:mod:`services.reasoner.prompts`) asks the model to end with one
line exactly ``FINAL ANSWER: <option number>``. The parser accepts an answer
only when there is no doubt; anything else raises :class:`ParseError` with a
short machine-readable ``reason`` and the caller falls back (never a guess):

- ``empty``: the text is empty or whitespace.
- ``injection``: the observation given tried to inject instructions.
- ``refusal``: no final answer, and the text reads as a refusal.
- ``no_answer``: no ``FINAL ANSWER:`` marker at all.
- ``multiple_answers``: the marker occurs more than once anywhere in the text,
  even mid-sentence and even with equal numbers. A rationale that quotes
  "FINAL ANSWER: 2" and then ends with ``FINAL ANSWER: 1`` is therefore
  rejected: the model has written two answers and we cannot tell which it meant.
- ``malformed``: the single marker is not on the last non-empty line, or that
  line is not exactly the marker and one non-negative ASCII integer ("1 or 2",
  "one", "-1", "２", "02", "1.0" are all malformed).
- ``not_offered``: a well-formed number outside ``offered``.

Tolerated on the final line: surrounding whitespace, any letter case of the
marker, one trailing period, and markdown emphasis or inline code made of
``*``, ``_`` or backticks (up to three) around the line, the marker or the
number: ``**FINAL ANSWER: 2**``, ``**FINAL ANSWER:** 2``, `` `FINAL ANSWER: 2` ``.
A code fence on its own line after the answer is not tolerated.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from shared.injection import tripwire, visible

Reason = Literal[
    "no_answer", "multiple_answers", "not_offered", "refusal", "injection", "empty", "malformed"
]

MAX_RATIONALE = 2000
MAX_DIGITS = 6

# Blanks, then optional emphasis (up to three of *, _, `) and blanks: the same texts as
# blanks, up to three emphasis characters, blanks, but in time linear in the line. The
# adjacent ``\s*[*_`]{0,3}\s*`` (three in a row after the number) backtracked over every
# split of a run of blanks: 800 spaces after the number took 1.4 s, 1,600 took 12 s.
_SPACED = r"\s*(?:[*_`]{1,3}\s*)?"
_FINAL_LINE = re.compile(
    rf"^{_SPACED}FINAL ANSWER\s*:{_SPACED}(0|[1-9][0-9]{{0,{MAX_DIGITS - 1}}})"
    rf"\s*(?:\.\s*)?(?:[*_`]{{1,3}}\s*)?$",
    re.IGNORECASE | re.ASCII,
)
_MARKER = re.compile(r"final\s*answer\W{0,3}:", re.IGNORECASE)
_REFUSAL = re.compile(
    r"\bi\s*(?:can't|cannot|can not|won't|will not|am unable to|am not able to|'m unable to)"
    r"\s+(?:help|assist|comply|provide|answer|do that|fulfil|make)"
    r"|\bas an ai\b|\bi'm sorry,? but\b|\bi am sorry,? but\b",
    re.IGNORECASE,
)


class ParseError(ValueError):
    """The model's text gives no certain choice; ``reason`` is a short machine code."""

    def __init__(self, reason: Reason, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason: Reason = reason
        self.detail = detail


@dataclass(frozen=True)
class Parsed:
    """y, the chosen option index, and the text before the final line (truncated)."""

    choice: int
    rationale: str


def parse_decision(text: str, offered: Sequence[int], *, observation: str | None = None) -> Parsed:
    """Parse ``text`` into a choice in ``offered``, or raise :class:`ParseError`."""
    allowed = _offered(offered)
    if observation is not None:
        flagged = tripwire(observation)
        if flagged:
            raise ParseError("injection", f"observation flagged ({flagged})")
    shown = visible(text)
    if not shown.strip():
        raise ParseError("empty", "no text")
    markers = len(_MARKER.findall(shown))
    if markers == 0:
        if _REFUSAL.search(shown.replace("\u2019", "'")):
            raise ParseError("refusal", "the model refused and gave no final answer")
        raise ParseError("no_answer", "no 'FINAL ANSWER:' line")
    if markers > 1:
        raise ParseError("multiple_answers", f"'FINAL ANSWER:' occurs {markers} times")
    lines = text.splitlines()
    last = max(i for i, line in enumerate(lines) if visible(line).strip())
    if not _MARKER.search(visible(lines[last])):
        raise ParseError("malformed", "the final answer is not the last line")
    match = _FINAL_LINE.match(lines[last])
    if match is None:
        raise ParseError("malformed", f"bad final line {_clip(lines[last].strip(), 80)!r}")
    choice = int(match.group(1))
    if choice not in allowed:
        raise ParseError("not_offered", f"option {choice} not in {sorted(allowed)}")
    return Parsed(choice=choice, rationale=_clip("\n".join(lines[:last]).strip(), MAX_RATIONALE))


def parse_partial(
    text_so_far: str, offered: Sequence[int], *, observation: str | None = None
) -> Parsed | None:
    """Early exit while streaming: a result only once certain, else None (never a guess).

    Certain means the text so far ends with a complete, valid final-answer line
    followed by a newline and parses under :func:`parse_decision`. Text after
    that point is not awaited: the prompt asks for the answer line to be last.
    """
    if not text_so_far.endswith(("\n", "\r")):
        return None
    try:
        return parse_decision(text_so_far, offered, observation=observation)
    except ParseError:
        return None


def _offered(offered: Sequence[int]) -> frozenset[int]:
    if not offered:
        raise ValueError("offered: must not be empty")
    for index in offered:
        if isinstance(index, bool) or not isinstance(index, int) or index < 0:
            raise ValueError(f"offered: indices must be non-negative ints, got {index!r}")
    return frozenset(offered)


def _clip(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "\u2026"
