"""Slow-reasoner prompts after the paper's prompting appendix (App. ap:prompting, §IV-A).

A prompt describes the robot and the runtime monitor's job, then gives the
current task, the observation o_t and the numbered options y in {0, 1..d}, and
ends with an output instruction (chain-of-thought or a single token) plus a
strict final-answer line. Rendered layout (the delimiters are a contract: the
fake LLM server and :mod:`services.reasoner.parsing` rely on them)::

    <robot paragraph>

    <monitor paragraph>

    Task:
    > <task>
    Observation:
    > <observation line 1>
    > <observation line 2>
    Unusual detections (nearest nominal detection, cosine similarity):
    > <detection> (nearest nominal: <detection>, 0.61)
    Options:
    0: continue nominal operation
    1: <label> — <description>

    <instruction>
    End your answer with one line exactly: FINAL ANSWER: <option number>

The ``Unusual detections`` block is there only when the anomaly detector named the
observation's odd detections (``ReasonerRequest.unusual``) or pair of detections
(``unusual_pair``: "a person together with a forklift (nearest nominal pair: ...)").

The task, the observation and the detections are untrusted text: every line is quoted
with ``"> "`` (the task and each detection are one line, line breaks folded to spaces) so
none can open its own ``Options:`` or ``FINAL ANSWER:`` line, and
:func:`suspicious_scene` flags any of them that trips the injection tripwire
(:func:`shared.injection.tripwire`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from functools import lru_cache
from importlib import resources
from typing import Literal

import yaml

from shared.injection import tripwire
from shared.messages import DetectionMatch, Option, PairMatch, ReasonerRequest

Variant = Literal["cot", "single"]
Named = DetectionMatch | PairMatch  # what the anomaly detector named of a scene


class PromptError(ValueError):
    """A request the prompt cannot be built from; ``field`` names what (``options``,
    ``observation``, ``options[2].label``) and the message starts with it."""

    def __init__(self, field: str, problem: str) -> None:
        super().__init__(f"{field}: {problem}")
        self.field = field

DOMAINS: tuple[str, ...] = ("quadrotor", "vtol", "warehouse", "vehicle")

CONTINUE_LINE = "0: continue nominal operation"
# in place of CONTINUE_LINE when the caller withholds 0 (the control loop, while the
# anomaly detector is silent): the instructions' "choose 0 only if ..." does not apply
CONTINUE_WITHHELD = "(0, continue nominal operation, is not available now: choose one of these)"
FINAL_INSTRUCTION = "End your answer with one line exactly: FINAL ANSWER: <option number>"
QUOTE = "> "
DASH = "\u2014"  # em dash between an option's label and its description


@dataclass(frozen=True)
class Template:
    """The fixed text of one domain's prompt; see the module docstring for the layout."""

    domain: str
    robot: str
    monitor: str
    cot_instruction: str
    single_token_instruction: str

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, str) or not value.strip():
                raise ValueError(f"{f.name}: must be a non-empty string")

    @property
    def description(self) -> str:
        """The robot and monitor paragraphs, separated by a blank line."""
        return f"{self.robot.strip()}\n\n{self.monitor.strip()}"

    def instruction(self, variant: Variant) -> str:
        """The output instruction for ``variant``, without the final-answer line."""
        if variant == "cot":
            return self.cot_instruction.strip()
        if variant == "single":
            return self.single_token_instruction.strip()
        raise ValueError(f"variant: must be 'cot' or 'single', got {variant!r}")


def load_template(domain: str) -> Template:
    """Load the packaged template ``templates/<domain>.yaml``."""
    if domain not in DOMAINS:
        raise ValueError(f"domain: unknown {domain!r}; known domains: {', '.join(DOMAINS)}")
    return _load(domain)


@lru_cache(maxsize=len(DOMAINS))
def _load(domain: str) -> Template:
    path = resources.files("services.reasoner").joinpath("templates", f"{domain}.yaml")
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    expected = {f.name for f in fields(Template)}
    if not isinstance(data, dict) or set(data) != expected:
        raise ValueError(f"template {domain}: keys must be exactly {sorted(expected)}")
    if data["domain"] != domain:
        raise ValueError(f"template {domain}: domain field says {data['domain']!r}")
    return Template(**data)


def build_prompt(
    template: Template,
    *,
    task: str,
    observation: str,
    options: Sequence[Option],
    variant: Variant = "cot",
    unusual: Sequence[Named] = (),
    drift: bool = False,
) -> str:
    """The single-string prompt: description, scene, instruction (module docstring layout)."""
    scene = render_scene(task=task, observation=observation, options=options, unusual=unusual,
                         drift=drift)
    return f"{template.description}\n\n{scene}\n\n{_instruction(template, variant)}"


def build_messages(
    template: Template,
    *,
    task: str,
    observation: str,
    options: Sequence[Option],
    variant: Variant = "cot",
    unusual: Sequence[Named] = (),
    drift: bool = False,
) -> list[dict[str, str]]:
    """OpenAI chat messages: system = description + instructions, user = the scene."""
    scene = render_scene(task=task, observation=observation, options=options, unusual=unusual,
                         drift=drift)
    system = f"{template.description}\n\n{_instruction(template, variant)}"
    return [{"role": "system", "content": system}, {"role": "user", "content": scene}]


UNUSUAL = "Unusual detections (nearest nominal detection, cosine similarity):"
# said, neutrally, while the detector drifts: it flags more than it promised, so its alarm
# says less than usual; the note names no phrase (those are other frames' words, for the
# operator: the drift event names them) and leans towards no answer
DRIFT = ("Note: over its recent scenes the anomaly detector has flagged far more than its "
         "calibration allows; it may be seeing new wording (a new captioner or camera) rather "
         "than new objects. Judge this observation on its own.")


def render_scene(*, task: str, observation: str, options: Sequence[Option],
                 unusual: Sequence[Named] = (), drift: bool = False) -> str:
    """The ``Task:`` / ``Observation:`` / [``Unusual detections:``] / [the drift note] /
    ``Options:`` block."""
    return (
        f"Task:\n{QUOTE}{_single_line(task, 'task')}\n"
        f"Observation:\n{quote_observation(observation)}\n"
        + (f"{UNUSUAL}\n{render_unusual(unusual)}\n" if unusual else "")
        + (f"{DRIFT}\n" if drift else "")
        + f"Options:\n{render_options(options)}"
    )


def unusual_of(request: ReasonerRequest) -> tuple[Named, ...]:
    """What the verdict that raised the anomaly named: its detections, then its pair."""
    pair = (request.unusual_pair,) if request.unusual_pair is not None else ()
    return (*request.unusual, *pair)


def unusual_line(match: Named) -> str:
    """"a keyboard on the ground (nearest nominal: a drill on the ground, 0.61)", or for
    a pair "a person together with a forklift (nearest nominal pair: a person with a
    shelf, 0.41)"."""
    def one(text: str) -> str:
        return " ".join(text.split())

    if isinstance(match, PairMatch):
        (a, b), (c, d) = match.detections, match.nearest
        return (f"{one(a)} together with {one(b)} (nearest nominal pair: {one(c)} with "
                f"{one(d)}, {match.similarity:.2f})")
    return f"{one(match.detection)} (nearest nominal: {one(match.nearest)}, " \
        f"{match.similarity:.2f})"


def render_unusual(unusual: Sequence[Named]) -> str:
    """One quoted line per detection the anomaly detector named."""
    return "\n".join(QUOTE + unusual_line(m) for m in unusual)


def _instruction(template: Template, variant: Variant) -> str:
    return f"{template.instruction(variant)}\n{FINAL_INSTRUCTION}"


def quote_observation(text: str) -> str:
    """Prefix every line of ``text`` with ``"> "``.

    Lines are split with :meth:`str.splitlines`, the widest notion of a line
    break, so no reader can find an unquoted line in the result.
    """
    if not isinstance(text, str) or not text.strip():
        raise PromptError("observation", "must be a non-empty string")
    return "\n".join(QUOTE + line.rstrip() for line in text.strip().splitlines())


def render_options(options: Sequence[Option]) -> str:
    """Option lines sorted by index; option 0 always reads ``continue nominal operation``,
    or, withheld (the control loop, while the detector is silent), says it is not
    available."""
    checked = validate_options(options)
    offered = checked[0].index == 0
    lines = [CONTINUE_LINE if offered else CONTINUE_WITHHELD]
    for opt in checked[1:] if offered else checked:
        label = _single_line(opt.label, f"options[{opt.index}].label")
        description = " ".join(opt.description.split())
        lines.append(
            f"{opt.index}: {label} {DASH} {description}" if description else f"{opt.index}: {label}"
        )
    return "\n".join(lines)


def validate_options(options: Sequence[Option]) -> tuple[Option, ...]:
    """Options sorted by index; not empty, unique indices, else PromptError. Option 0
    (continue) may be withheld, never anything else required."""
    if not options:
        raise PromptError("options", "must not be empty")
    seen: set[int] = set()
    for opt in options:
        if not isinstance(opt, Option):
            raise PromptError("options", f"expected Option, got {type(opt).__name__}")
        if opt.index in seen:
            raise PromptError("options", f"duplicate index {opt.index}")
        seen.add(opt.index)
    return tuple(sorted(options, key=lambda o: o.index))


def _single_line(text: str, field: str) -> str:
    collapsed = " ".join(text.split()) if isinstance(text, str) else ""
    if not collapsed:
        raise PromptError(field, "must be a non-empty string")
    return collapsed


def suspicious_scene(*, task: str, observation: str,
                     unusual: Sequence[Named] = ()) -> str | None:
    """Which of the scene's untrusted texts tries to inject instructions, and how
    (``task flagged (...)``, ``observation flagged (...)``, ``detections flagged
    (...)``), else None."""
    named = "\n".join(unusual_line(m) for m in unusual)
    for name, text in (("observation", observation), ("task", task), ("detections", named)):
        flagged = tripwire(text)
        if flagged:
            return f"{name} flagged ({flagged})"
    return None
