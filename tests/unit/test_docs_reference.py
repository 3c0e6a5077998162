"""docs/architecture.md's three references against the code they describe (issue 45: the
module list had missed 12 modules): the module list of section 2 names every module of
``shared``, ``services`` and ``tools`` under its folder and nothing that is not there (the
list is generated now, tests/unit/test_reference.py; this reads the page against the files
on disk, so a folder the generator skipped would show here); the CLI table of section 6 has
a row for every command of the tree; section 7 names every variable each service reads and
every knob of its groups, and no variable nobody reads. Each check is shown failing on a
page that drifted (a check that cannot fail is a defect)."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from pydantic import BaseModel
from pydantic_settings import BaseSettings

from services.control.settings import ControlSettings
from services.dashboard.settings import DashboardSettings
from services.embedding.settings import EmbeddingSettings
from services.reasoner.settings import ReasonerSettings
from services.ros2.settings import Ros2Settings
from services.sim.settings import SimSettings
from shared.settings import env_names
from tools import cli
from tools.fakes.llm import FakeLLMServiceSettings, FakeLLMSettings

ROOT = Path(__file__).resolve().parents[2]
PAGE = (ROOT / "docs" / "architecture.md").read_text()


def section(text: str, heading: str) -> str:
    start = text.index(f"\n## {heading}")
    end = text.find("\n## ", start + 1)
    return text[start:end if end > 0 else len(text)]


# -- the module list (section 2) -----------------------------------------------------------

# a row of the list: its indent (two spaces a floor) and a folder or a module; a description's
# continuation lines are indented further, and `the shell:` (a service's own modules) names none
ROW = re.compile(r"^((?:  ){0,4})([a-z0-9_]+/|[a-z0-9_]+\.py)(?=\s|$)")


def listed(text: str) -> dict[str, set[str]]:
    """The module list's names by the folder they are listed under: ``{"services/embedding/
    detector": {"cache.py", ...}, ...}``. The list is a tree: a module's folder is the folders
    above it, each one indent further out."""
    block = section(text, "2. Layout").split("```")[1]
    names: dict[str, set[str]] = {}
    folders: list[str] = []
    for line in block.splitlines():
        match = ROW.match(line)
        if match is None:
            continue
        depth, name = len(match.group(1)) // 2, match.group(2)
        if name.endswith("/"):
            folders[depth:] = [name.rstrip("/")]
        else:
            names.setdefault("/".join(folders[:depth]), set()).add(name)
    return names


def modules() -> Iterator[tuple[str, str]]:
    """(folder, file name) of every module but a package's ``__init__``."""
    for top in ("shared", "services", "tools"):
        for path in (ROOT / top).rglob("*.py"):
            if path.name != "__init__.py" and "__pycache__" not in path.parts:
                yield str(path.parent.relative_to(ROOT)), path.name


def list_drift(text: str) -> list[str]:
    shown = {(folder, name) for folder, found in listed(text).items() for name in found}
    present = set(modules())
    return [f"not listed: {folder}/{name}" for folder, name in sorted(present - shown)] + \
        [f"listed, not there: {folder}/{name}" for folder, name in sorted(shown - present)]


def test_the_module_list_names_every_module_and_nothing_else() -> None:
    assert list_drift(PAGE) == []


def test_the_module_list_check_catches_a_missing_and_a_stale_module() -> None:
    drifted = PAGE.replace("      drift.py         Drift:", "      drift2.py        Drift:")
    assert drifted != PAGE
    assert list_drift(drifted) == ["not listed: services/embedding/detector/drift.py",
                                   "listed, not there: services/embedding/detector/drift2.py"]


# -- the CLI table (section 6) ---------------------------------------------------------------

def leaves(parser: argparse.ArgumentParser, path: tuple[str, ...] = ("aesop",)
           ) -> Iterator[str]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield " ".join(path)
        return
    for name, child in subs[0].choices.items():
        yield from leaves(child, (*path, name))


def cli_drift(text: str) -> list[str]:
    rows = [line.split("|")[1] for line in section(text, "6. CLI").splitlines()
            if line.startswith("| `aesop")]
    return [command for command in leaves(cli.build_parser())
            if not any(re.search(rf"`{re.escape(command)}(?![\w-])", row) for row in rows)]


def test_the_cli_table_has_a_row_for_every_command() -> None:
    assert cli_drift(PAGE) == []


def test_the_cli_check_catches_a_command_without_a_row() -> None:
    drifted = "\n".join(line for line in PAGE.splitlines()
                        if not line.startswith("| `aesop bench fairness`"))
    assert cli_drift(drifted) == ["aesop bench fairness"]


# -- the settings (section 7) ----------------------------------------------------------------

SETTINGS: list[type[BaseSettings]] = [EmbeddingSettings, ReasonerSettings, ControlSettings,
                                      SimSettings, Ros2Settings, DashboardSettings,
                                      FakeLLMServiceSettings, FakeLLMSettings]
# every HTTP service has these; section 7 gives them one row each, AESOP_<SERVICE>_...
PER_SERVICE = {"host", "port", "max_body_bytes"}


def variables() -> dict[str, type[BaseModel] | None]:
    """Every variable a service reads, with the group of knobs it holds (None: a value)."""
    out: dict[str, type[BaseModel] | None] = {}
    for cls in SETTINGS:
        for name, field in cls.model_fields.items():
            if name in PER_SERVICE:
                continue
            kind = field.annotation
            group = kind if isinstance(kind, type) and issubclass(kind, BaseModel) else None
            out[env_names(cls, name)[0]] = group
    return out


def parts(text: str) -> list[str]:
    """Each table row and each paragraph."""
    return re.split(r"\n\s*\n|\n(?=\|)", text)


def paragraph(text: str, needle: str) -> str:
    """The table row, or the paragraph, that names ``needle``."""
    return next((part for part in parts(text) if needle in part), "")


def settings_drift(text: str) -> list[str]:
    page = section(text, "7. Settings")
    fake = page[page.find("**fake LLM**"):]  # its paragraph and its table (tools/reference.py)
    problems = []
    known = variables()
    for variable, group in sorted(known.items()):
        if f"`{variable}`" not in page:
            problems.append(f"not named: {variable}")
        elif group is not None:
            row = paragraph(page, f"`{variable}`")
            problems += [f"not named: {variable}'s {knob}" for knob in group.model_fields
                         if f"`{knob}`" not in row]
    for short in FakeLLMSettings.model_fields:  # its own knobs, in its table
        if f"`AESOP_FAKE_LLM_{short.upper()}`" not in fake:
            problems.append(f"not named: AESOP_FAKE_LLM_{short.upper()}")
    # the tables and the services' paragraphs (the prose names prefixes and the old flat
    # names that are pointed to new ones)
    rows = [part for part in parts(page)
            if part.startswith("|") or re.match(r"\*\*[\w ]+\*\* \(`", part)]
    said = set(re.findall(r"`(AESOP_[A-Z0-9_]*[A-Z0-9])`", "\n".join(rows)))
    for variable in sorted(said - set(known)):
        group, _, knob = variable.partition("__")
        if knob and known.get(group) is not None and knob.lower() in known[group].model_fields:
            continue
        if any(variable.endswith(f"_{knob.upper()}") for knob in PER_SERVICE):
            continue  # the per-service rows' examples (AESOP_SIM_PORT, AESOP_FAKE_LLM_HOST)
        problems.append(f"named, read by nobody: {variable}")
    return problems


def test_the_settings_section_names_every_variable_and_knob_and_nothing_else() -> None:
    assert settings_drift(PAGE) == []


@pytest.mark.parametrize(("old", "new", "found"), [
    ("`AESOP_CONTROL_METHOD`", "`AESOP_CONTROL_MEHTOD`",
     ["not named: AESOP_CONTROL_METHOD", "named, read by nobody: AESOP_CONTROL_MEHTOD"]),
    ("`drift_significance`", "`drift_signif`",
     ["not named: AESOP_EMBEDDING_ADAPT's drift_significance"]),
])
def test_the_settings_check_catches_a_misspelt_variable_and_a_missing_knob(
        old: str, new: str, found: list[str]) -> None:
    drifted = PAGE.replace(old, new)
    assert drifted != PAGE
    assert settings_drift(drifted) == found
