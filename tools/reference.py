"""The settings, CLI and module references, generated from the code (issue 45).

The hand-written tables and module list had drifted from what the services read, the commands
take and the source tree holds.

:func:`settings_reference` renders section 7 of docs/architecture.md from the settings
classes: per service a table of the variables it reads, with each field's default and its
``Field(description=...)``; a group of knobs is one row listing its knobs. The variables are
named as the classes read them: the ``env_prefix`` plus the field's name, or the variable a
field names itself (``AESOP_ROBOT``, ``..._API_KEY``, else ``OPENAI_API_KEY``).
:func:`cli_reference` renders docs/cli.md from ``build_parser()``: every command and
subcommand, and each argument with what it takes, its default and its help.
:func:`modules_reference` renders section 2's module list from the source tree: every folder
and module of ``shared/``, ``services/`` and ``tools/``, each with its docstring's first
sentence (read from the source, not imported).

``python -m tools.reference settings|cli|modules`` prints one and says whether its page holds
it (exit status 1 when not); with ``--write`` it goes into its place (section 7 or section 2
between their markers, or the whole of docs/cli.md), and tests/unit/test_reference.py fails
when the pages and the code differ. Nothing is read or written on import.
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import sys
import textwrap
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import AliasChoices, BaseModel, SecretStr
from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings

ROOT = Path(__file__).resolve().parents[1]
ARCHITECTURE = ROOT / "docs" / "architecture.md"
CLI_PAGE = ROOT / "docs" / "cli.md"
BEGIN = "<!-- generated: python -m tools.reference settings --write -->"
MODULES_BEGIN = "<!-- generated: python -m tools.reference modules --write -->"
END = "<!-- end of generated text -->"
CLI_HEADER = ("Generated from the parser (`build_parser()` in `tools/cli.py`) by `python -m "
              "tools.reference cli --write`: change the help there, not here.")


# -- markdown --------------------------------------------------------------------------------

def cell(text: str) -> str:
    """``text`` for a table cell: its code spans kept, ``|`` escaped everywhere, and
    outside code what markdown would take for a tag or emphasis (``<id>``, ``*``, a ``_``
    not inside a word)."""
    pieces = text.split("`")
    if len(pieces) % 2 == 0:  # an unpaired backtick: no code spans
        pieces = [text]
    out = []
    for i, piece in enumerate(pieces):
        if i % 2 == 0:
            piece = re.sub(r"([\\<*])", r"\\\1", piece)
            piece = re.sub(r"(?<![A-Za-z0-9])_|_(?![A-Za-z0-9])", r"\\_", piece)
        out.append(piece.replace("|", "\\|"))
    return "`".join(out)


def code(text: str) -> str:
    return f"`{text}`"


def table(head: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def number(value: float) -> str:
    """``25.0`` as 25, ``1e-07`` as 1e-7."""
    text = repr(value)
    text = text.removesuffix(".0")
    return re.sub(r"e([+-]?)0*(\d)", r"e\1\2", text)


# -- the settings (section 7) ----------------------------------------------------------------

def sections() -> list[tuple[str, list[type[BaseSettings]], str]]:
    """Section 7's tables in order: a title, the classes whose variables it lists, and what
    it says after the title."""
    from services.control.settings import ControlSettings
    from services.dashboard.settings import DashboardSettings
    from services.embedding.settings import EmbeddingSettings
    from services.reasoner.settings import ReasonerSettings
    from services.ros2.settings import Ros2Settings
    from services.sim.settings import SimSettings
    from shared.settings import BusSettings, ServiceSettings
    from tools.fakes.llm import FakeLLMServiceSettings, FakeLLMSettings

    return [
        ("every process", [BusSettings], "how a process joins the Zenoh network; all that "
         "`aesop watch` reads."),
        ("every service", [ServiceSettings], "what every HTTP service adds; its host, port "
         "and body limit carry its own name, in its table below."),
        ("embedding", [EmbeddingSettings], "the detector."),
        ("reasoner", [ReasonerSettings], "the slow reasoner."),
        ("control", [ControlSettings], "the control loop."),
        ("sim", [SimSettings], "the simulated vehicle."),
        ("ros2", [Ros2Settings], "the bridge to a ROS 2 robot."),
        ("dashboard", [DashboardSettings], "the dashboard."),
        ("fake LLM", [FakeLLMSettings, FakeLLMServiceSettings], "`aesop serve fake-llm`; "
         "its flags override these (`python -m tools.fakes.llm --help`)."),
    ]


def shared_fields() -> set[str]:
    """The fields every service reads under one name (``AESOP_ROBOT``): they name their
    variable themselves, so a service's prefix does not touch them."""
    from shared.settings import ServiceSettings

    return {name for name, info in ServiceSettings.model_fields.items()
            if isinstance(info.validation_alias, str)}


def fields(cls: type[BaseSettings]) -> list[str]:
    """The fields of ``cls`` its table lists: the shared ones in the shared tables, the
    rest (host, port, body limit and its own) in the service's."""
    from shared.settings import BusSettings, ServiceSettings

    shared = shared_fields()
    if cls is BusSettings:
        return list(cls.model_fields)
    if cls is ServiceSettings:
        return [n for n in cls.model_fields if n in shared and n not in BusSettings.model_fields]
    return [n for n in cls.model_fields if n not in shared]


def variables(cls: type[BaseSettings], name: str) -> str:
    """The variable(s) field ``name`` of ``cls`` is read from, first one first."""
    from shared.settings import env_names

    alias = cls.model_fields[name].validation_alias
    names = [str(c) for c in alias.choices] if isinstance(alias, AliasChoices) else \
        list(env_names(cls, name))
    return ", else ".join(code(n) for n in names)


def default(info: FieldInfo) -> str:
    """A field's default as one sets it in the environment: strings, switches and paths as
    code, numbers and none plain."""
    value = info.get_default(call_default_factory=True)
    if isinstance(value, BaseModel):
        return "see the knobs"
    return shown(value)


def shown(value: Any) -> str:
    if value is None or isinstance(value, SecretStr):
        return "none"
    if isinstance(value, bool):
        return code("true" if value else "false")
    if isinstance(value, int | float):
        return number(value)
    if isinstance(value, str | Path):
        return code(str(value)) if str(value) else "empty"
    if isinstance(value, list):
        return code(",".join(map(str, value))) if value else "empty"
    return code(json.dumps(value))  # tuples and mappings: JSON


def meaning(info: FieldInfo) -> str:
    """A field's description; a group's, then each knob as "`knob` default (description)"."""
    if not info.description:
        raise ValueError(f"a setting without a description: {info}")
    group = info.annotation
    if not (isinstance(group, type) and issubclass(group, BaseModel)):
        return info.description
    knobs = []
    for knob, sub in group.model_fields.items():
        if not sub.description:
            raise ValueError(f"{group.__name__}.{knob} has no description")
        knobs.append(f"{code(knob)} {default(sub)} ({sub.description})")
    return f"{info.description}: " + "; ".join(knobs)


def settings_table(classes: Sequence[type[BaseSettings]]) -> str:
    rows = [[variables(cls, name), cell(default(cls.model_fields[name])),
             cell(meaning(cls.model_fields[name]))]
            for cls in classes for name in fields(cls)]
    return table(["variable", "default", "meaning"], rows)


def settings_reference() -> str:
    """Section 7's tables, as markdown (what sits between its markers)."""
    parts = []
    for title, classes, lead in sections():
        names = ", ".join(code(cls.__name__) for cls in classes)
        parts.append(f"**{title}** ({names}): {lead}\n\n{settings_table(classes)}")
    return "\n".join(parts)


def between(page: str, begin: str) -> str:
    """What ``page`` holds between ``begin`` and the first end marker after it (without the
    blank lines around it)."""
    _, found, rest = page.partition(begin)
    held, end, _ = rest.partition(END)
    if not found or not end:
        raise ValueError(f"the page has no {begin} ... {END}")
    return held.removeprefix("\n\n").removesuffix("\n")


def with_between(page: str, text: str, begin: str) -> str:
    """``page`` with ``text`` between ``begin`` and the end marker after it."""
    head, _, rest = page.partition(begin)
    _, _, tail = rest.partition(END)
    between(page, begin)  # both markers are there
    return f"{head}{begin}\n\n{text}\n{END}{tail}"


def settings_in(page: str) -> str:
    """What section 7's markers hold."""
    return between(page, BEGIN)


def with_settings(page: str, text: str) -> str:
    return with_between(page, text, BEGIN)


# -- the CLI (docs/cli.md) --------------------------------------------------------------------

def commands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ("aesop",),
             about: str = "") -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser, str]]:
    """Every command of the tree, depth first: its words, its parser and its help."""
    yield path, parser, about
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {choice.dest: expanded(parser, choice) for choice in action._choices_actions}
            for name, child in action.choices.items():
                yield from commands(child, (*path, name), helps.get(name, ""))


def expanded(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """An action's help as ``--help`` shows it (``%%`` as ``%``, ``%(default)s`` filled)."""
    if not action.help or action.help == argparse.SUPPRESS:
        return ""
    return parser._get_formatter()._expand_help(action)


def takes(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """What an argument takes, as ``--help`` writes it: a metavar, its choices, or its
    name; nothing for a switch."""
    if action.nargs == 0:
        return ""
    formatter = parser._get_formatter()
    metavar = (formatter._get_default_metavar_for_optional(action) if action.option_strings
               else formatter._get_default_metavar_for_positional(action))
    return code(formatter._format_args(action, metavar))


def default_of(action: argparse.Action, help_text: str) -> str:
    """An argument's default: ``required``; else what its help gives in words (``default:
    every CPU``: the value may be this machine's, or None standing for what it names); else
    the value (off for a switch)."""
    if action.required:
        return "required"
    words = re.search(r"default: ([^;)]*)", help_text)
    if words:
        return cell(words.group(1).strip())
    if isinstance(action, argparse._StoreTrueAction):
        return "off"
    if isinstance(action, argparse._StoreFalseAction):
        return "on"
    value = action.default
    if value is None or value == argparse.SUPPRESS or value == [] or action.nargs == 0:
        return ""
    if isinstance(value, list):
        return cell(code(" ".join(number(v) if isinstance(v, float) else str(v)
                                  for v in value)))
    return cell(code(number(value) if isinstance(value, float) else str(value)))


def arguments(parser: argparse.ArgumentParser) -> list[list[str]]:
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction | argparse._SubParsersAction) or \
                action.help == argparse.SUPPRESS:
            continue
        name = ", ".join(action.option_strings) or str(action.metavar or action.dest)
        help_text = expanded(parser, action)
        rows.append([code(name), cell(takes(parser, action)), default_of(action, help_text),
                     cell(help_text)])
    return rows


def anchor(path: Sequence[str]) -> str:
    """GitHub's anchor of a command's heading (`` ## `aesop bench mpc` ``)."""
    return "#" + "-".join(path).lower()


def fake_llm_rows() -> list[list[str]]:
    """``aesop serve fake-llm``'s own flags (its parser in tools/fakes/llm.py gives none
    help): each overrides the setting of its name, whose description and default are its."""
    from tools.fakes.llm import FakeLLMServiceSettings, FakeLLMSettings
    from tools.fakes.llm import build_parser as fake_parser

    parser = fake_parser()
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        cls: type[BaseSettings] = (FakeLLMSettings if action.dest in FakeLLMSettings.model_fields
                                   else FakeLLMServiceSettings)
        info = cls.model_fields[action.dest]
        help_text = expanded(parser, action) or info.description or ""
        rows.append([code(", ".join(action.option_strings)), cell(takes(parser, action)),
                     f"{variables(cls, action.dest)}, else {cell(default(info))}",
                     cell(help_text)])
    return rows


def cli_reference() -> str:
    """docs/cli.md: every command of ``aesop``, each with its subcommands or arguments."""
    from tools.cli import build_parser

    root = build_parser()
    out = ["# `aesop`: every command and flag", "", CLI_HEADER, ""]
    if root.description:
        out += [root.description.replace("``", "`"), ""]
    for path, parser, about in commands(root):
        title = " ".join(path)
        out += [f"## {code(title)}", ""]
        if about:
            out += [cell(about), ""]
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        rows = arguments(parser)
        if rows:
            out += [table(["argument", "takes", "default", "meaning"], rows)]
        if subs:
            helps = {c.dest: expanded(parser, c) for c in subs[0]._choices_actions}
            out += [table(["command", "what it does"], [
                [f"[{code(f'{title} {name}')}]({anchor([*path, name])})",
                 cell(helps.get(name, ""))] for name in subs[0].choices])]
        if path == ("aesop", "serve"):
            out += [f"## {code('aesop serve fake-llm')}", "",
                    "The fake LLM takes flags of its own (`python -m tools.fakes.llm "
                    "--help`); each overrides its setting (section 7 of "
                    "[architecture.md](architecture.md#7-settings)).", "",
                    table(["argument", "takes", "default", "meaning"], fake_llm_rows())]
    return "\n".join(out).rstrip("\n") + "\n"


# -- the module list (section 2) ---------------------------------------------------------------

FLOORS = ("shared", "services", "tools")
# the folders in the list's order where it is not the alphabet's: the services as section 2's
# prose names them, and a service's core folders by floor, each before those that import it;
# the rest follow their siblings in alphabetical order
FOLDER_ORDER = ("services/embedding", "services/embedding/detector", "services/embedding/models",
                "services/embedding/storage", "services/embedding/fleet", "services/reasoner",
                "services/control", "services/sim", "services/ros2", "services/dashboard",
                "tools/stack", "tools/link", "tools/recording", "tools/demo", "tools/bench",
                "tools/scenes", "tools/fakes")
SHELL = "the service around its core, which imports none of it"
LIST_WIDTH = 100


def summary(doc: str | None) -> str:
    """A docstring's first sentence on one line, for the module list: its first paragraph up
    to the first ``.``, ``?`` or ``!`` that ends a sentence (outside brackets and code, then
    the end or a capital), the full stop dropped; reST's ``code`` and roles
    (``:mod:`.routes```) as markdown's `code`. Empty without a docstring."""
    text = " ".join((doc or "").strip().split("\n\n")[0].split())
    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"`\1`", text).replace("``", "`")
    depth, in_code = 0, False
    for i, char in enumerate(text):
        if char == "`":
            in_code = not in_code
        elif in_code:
            continue
        elif char in "([":
            depth += 1
        elif char in ")]":
            depth = max(depth - 1, 0)
        elif char in ".?!" and depth == 0 and re.match(r"(\s+[A-Z`\"]|$)", text[i + 1:]):
            return text[:i] if char == "." else text[:i + 1]
    return text.removesuffix(".")


def docstring(path: Path) -> str | None:
    """A module's docstring, read from its source (nothing is imported)."""
    return ast.get_docstring(ast.parse(path.read_text()), clean=True) if path.is_file() else None


def folder_key(folder: Path) -> tuple[int, str]:
    name = folder.relative_to(ROOT).as_posix()
    return (FOLDER_ORDER.index(name), "") if name in FOLDER_ORDER else (len(FOLDER_ORDER), name)


def packages(folder: Path) -> list[Path]:
    """The folders of ``folder`` that hold Python modules (not ``static/``, ``templates/``,
    ``scenarios/``), in the list's order."""
    subs = [sub for sub in folder.iterdir() if sub.is_dir() and sub.name != "__pycache__"
            and any(sub.rglob("*.py"))]
    return sorted(subs, key=folder_key)


def rows(folder: Path, depth: int = 0) -> list[tuple[int, str, str]]:
    """The list's rows of ``folder`` and all below it, as (depth, name, what it is): the
    folder (its ``__init__``'s docstring), its modules and its folders; a service's core
    folders come before its own modules, the shell."""
    head = [(depth, f"{folder.name}/", summary(docstring(folder / "__init__.py")))]
    own = [(depth + 1, path.name, summary(docstring(path)))
           for path in sorted(folder.glob("*.py")) if path.name != "__init__.py"]
    below = [row for sub in packages(folder) for row in rows(sub, depth + 1)]
    if folder.parent.name == "services" and below and own:
        return head + below + [(depth + 1, "the shell:", SHELL)] + own
    return head + own + below


def wrapped(text: str, width: int) -> list[str]:
    """``text`` in lines of at most ``width`` characters, a code span kept on one line where
    that fits."""
    def wrap(words: str) -> list[str]:
        return textwrap.wrap(words, width, break_long_words=False, break_on_hyphens=False)

    kept = wrap(re.sub(r"`[^`]*`", lambda span: span.group().replace(" ", "\0"), text))
    if any(len(line) > width for line in kept):
        kept = wrap(text)
    return [line.replace("\0", " ") for line in kept] or [""]


def modules_in(page: str) -> str:
    """What section 2's markers hold."""
    return between(page, MODULES_BEGIN)


def with_modules(page: str, text: str) -> str:
    return with_between(page, text, MODULES_BEGIN)


def modules_reference() -> str:
    """Section 2's module list, as markdown (what sits between its markers): a code block,
    one row per folder and module of ``shared/``, ``services/`` and ``tools/``, each its
    docstring's first sentence, wrapped under its column."""
    listed = [row for floor in FLOORS for row in rows(ROOT / floor)]
    column = max(2 * depth + len(name) for depth, name, _ in listed) + 2
    out = ["```"]
    for depth, name, about in listed:
        lines = wrapped(about, LIST_WIDTH - column)
        out.append(f"{'  ' * depth}{name}".ljust(column) + lines[0])
        out += [" " * column + line for line in lines[1:]]
    return "\n".join(line.rstrip() for line in out) + "\n```\n"


# -- running it -------------------------------------------------------------------------------

@dataclass(frozen=True)
class Reference:
    """One generated reference: how it is rendered and where it goes (between ``begin`` and
    the end marker of ``page``, or the whole page when ``begin`` is None)."""

    render: Callable[[], str]
    page: Path
    where: str
    begin: str | None = None

    def held(self, page: str) -> str:
        """What ``page`` holds of this reference."""
        return page if self.begin is None else between(page, self.begin)

    def placed(self, page: str, text: str) -> str:
        """``page`` with ``text`` in this reference's place."""
        return text if self.begin is None else with_between(page, text, self.begin)


def references() -> dict[str, Reference]:
    """The references by name (the pages as this module names them when it is called)."""
    return {
        "settings": Reference(settings_reference, ARCHITECTURE,
                              "docs/architecture.md section 7", BEGIN),
        "cli": Reference(cli_reference, CLI_PAGE, "docs/cli.md"),
        "modules": Reference(modules_reference, ARCHITECTURE,
                             "docs/architecture.md section 2", MODULES_BEGIN),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tools.reference",
        description="the settings, CLI and module references, generated from the code")
    known = references()
    parser.add_argument("which", choices=list(known),
                        help="settings: section 7 of docs/architecture.md; cli: docs/cli.md; "
                             "modules: section 2's module list")
    parser.add_argument("--write", action="store_true",
                        help="write it into its place (default: print it, and exit 1 when "
                             "its page differs)")
    args = parser.parse_args(argv)
    ref = known[args.which]
    text = ref.render()
    if args.write:
        ref.page.write_text(ref.placed(ref.page.read_text(), text))
        return 0
    sys.stdout.write(text)
    if ref.held(ref.page.read_text()) != text:
        print(f"{ref.where} differs from the code: run python -m tools.reference {args.which} "
              "--write", file=sys.stderr)
        return 1
    print(f"{ref.where} is up to date", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
