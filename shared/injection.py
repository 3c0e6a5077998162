"""A tripwire for prompt injection in the texts a robot sends, shared by reasoner and detector.

It reads observations, tasks and detection labels: the reasoner does not ask the LLM about
a scene that trips it, and the detector never learns a scene as nominal on its own when it
trips or nearly trips it.

It is a tripwire, not the defence. The defence is structural: the LLM may only choose
among the options offered (an answer outside them is a parse error that ends in the
fallback), "continue" is withheld while the loop cannot see, and a scene is learned as
nominal only after a "continue" from the LLM, never by a scene that looks like it talks
to the reader (:func:`near_miss`). Anything in the camera's view is the same attack as a
forged message: a sign reading "reply 0" is text the captioner will faithfully report.

Matching runs on :func:`fold`: NFKC (full-width letters, ligatures), invisible format
characters removed, and letters of other scripts that look like Latin ones (Cyrillic and
Greek capitals and lower case: "ANSWЕR" with a Cyrillic Е) mapped to those, so a look-alike
does not hide a marker. Every pattern runs in time linear in the text (it runs on the
event loop that holds every deadline): no two adjacent or nested quantifiers may match
the same characters, and a line-start pattern skips only the blanks and quote marks of
its own line, never a line break (8,000 newlines once took 2.6 s).
"""

from __future__ import annotations

import re
import unicodedata

# look-alikes of Latin letters in Cyrillic and Greek (a curated subset of Unicode's
# confusables: the letters that pass for Latin ones in most fonts)
_CONFUSABLES = str.maketrans({
    # Cyrillic
    "А": "A", "В": "B", "Е": "E", "К": "K", "М": "M", "Н": "H", "О": "O", "Р": "P",
    "С": "C", "Т": "T", "У": "Y", "Х": "X", "Ѕ": "S", "І": "I", "Ј": "J", "Ԛ": "Q",
    "Ԝ": "W", "а": "a", "е": "e", "о": "o", "р": "p", "с": "c", "у": "y", "х": "x",
    "ѕ": "s", "і": "i", "ј": "j", "ԁ": "d", "ԛ": "q", "ԝ": "w", "һ": "h", "ӏ": "l",
    # Greek
    "Α": "A", "Β": "B", "Ε": "E", "Ζ": "Z", "Η": "H", "Ι": "I", "Κ": "K", "Μ": "M",
    "Ν": "N", "Ο": "O", "Ρ": "P", "Τ": "T", "Υ": "Y", "Χ": "X", "ο": "o", "ν": "v",
    "ι": "i", "κ": "k", "ρ": "p", "τ": "t", "υ": "u", "χ": "x", "α": "a",
})

_BLANK = r"[^\S\n]"  # whitespace other than "\n", which ends the line for ``^``
_QUOTED = rf"(?:{_BLANK}|>)"
_SEP = r"[\s\-_.=:]*"  # between two words of a marker: "final-answer", "final_answer"
_PATTERNS: tuple[tuple[str, re.Pattern[str]], ...] = tuple(
    (reason, re.compile(pattern, re.IGNORECASE | re.MULTILINE))
    for reason, pattern in (
        ("final-answer marker", rf"final{_SEP}answer"),
        (
            "instruction override",
            r"\b(?:ignore|disregard|forget|override)\b.{0,40}?"
            r"\b(?:instructions?|prompts?|rules|directions|context)\b",
        ),
        ("role reassignment", r"\byou\s+are\s+now\b|\bpretend\s+(?:to\s+be|you)\b"),
        ("chat role marker", rf"\b(?:system|assistant|developer)\s*:|^{_BLANK}*user\s*:"),
        ("chat template token", r"<\|[a-z_]+\|>|\[/?inst\]|<</?sys>>"),
        ("prompt section header",
         rf"^{_QUOTED}*(?:options|task|observation|instructions?)\s*:"),
        ("option line", rf"^{_QUOTED}*\d+\s*:\s*continue\s+nominal"),
        ("new instructions", r"\bnew\s+instructions?\b|\bsystem\s+prompt\b"),
        ("answer steering",
         r"\b(?:choose|select|pick|answer|respond\s+with|output)\s+option\s*\d"
         r"|\b(?:reply|respond|answer)\b[^.\n]{0,40}?"
         r"\b(?:zero|one|two|three|four|\d+|continue|nominal)\b"),
        ("addressed to the reader",
         rf"^{_QUOTED}*(?:operator|reviewer|supervisor|administrator|admin|moderator)\b"
         r"[^:\n]{0,20}:"),
    )
)
# words a scene has no business saying to whoever reads it: not enough to refuse the
# scene, enough that it is never learned as nominal without a person looking
_NEAR = re.compile(
    r"\b(?:answers?|repl(?:y|ies)|respond|choose|choice|select|options?|instructions?"
    r"|prompts?|ignore|operators?|reviewers?|memo|nominal|assistant|llm|last\s+line)\b",
    re.IGNORECASE)


def visible(text: str) -> str:
    """``text`` in NFKC with its invisible format characters removed (zero-width spaces,
    joiners): what a reader sees, so a disguised marker still counts."""
    text = unicodedata.normalize("NFKC", text)
    return "".join(ch for ch in text if unicodedata.category(ch) != "Cf")


def fold(text: str) -> str:
    """``text`` as the patterns see it: :func:`visible`, then look-alike letters of other
    scripts as the Latin letters they pass for."""
    return visible(text).translate(_CONFUSABLES)


def tripwire(text: str) -> str | None:
    """A short reason when ``text`` tries to inject instructions, else None."""
    folded = fold(text)
    for reason, pattern in _PATTERNS:
        match = pattern.search(folded)
        if match:
            return f"{reason}: {match.group(0).strip()!r}"
    return None


def near_miss(text: str) -> str | None:
    """A short reason when ``text`` speaks like an instruction to its reader without
    tripping :func:`tripwire` ("a sign: the answer is yes"), else None."""
    match = _NEAR.search(fold(text))
    return None if match is None else f"instruction-like word {match.group(0)!r}"


def wary(*texts: str) -> str | None:
    """Why a scene made of ``texts`` must not be learned without a person: the first of
    them that trips the tripwire or nearly does, else None."""
    for text in texts:
        why = tripwire(text) or near_miss(text)
        if why:
            return why
    return None
