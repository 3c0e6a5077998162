"""The settings, CLI and module references are generated from the code (issue 45: the
hand-written tables and module list drifted): section 7 of docs/architecture.md, between its
markers, is what ``settings_reference()`` renders from the settings classes, section 2's
module list what ``modules_reference()`` renders from the modules' docstrings, and
docs/cli.md is what ``cli_reference()`` renders from the parser. Each check is shown failing
on a changed description (a check that cannot fail is a defect)."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import BaseModel

from services.embedding.settings import EmbeddingAdapt, EmbeddingSettings
from tools import reference
from tools.fakes.llm import FakeLLMSettings

ROOT = Path(__file__).resolve().parents[2]
PAGE = (ROOT / "docs" / "architecture.md").read_text()
CLI_PAGE = (ROOT / "docs" / "cli.md").read_text()
SETTINGS_FIX = "run `python -m tools.reference settings --write` (and commit docs/architecture.md)"
CLI_FIX = "run `python -m tools.reference cli --write` (and commit docs/cli.md)"
MODULES_FIX = "run `python -m tools.reference modules --write` (and commit docs/architecture.md)"


def settings_drift(page: str) -> str | None:
    """What to do when section 7's generated text is not what the code renders."""
    return None if reference.settings_in(page) == reference.settings_reference() else \
        f"docs/architecture.md section 7 differs from the settings classes: {SETTINGS_FIX}"


def modules_drift(page: str) -> str | None:
    """What to do when section 2's module list is not what the modules' docstrings render."""
    return None if reference.modules_in(page) == reference.modules_reference() else \
        f"docs/architecture.md section 2's module list differs from the modules: {MODULES_FIX}"


def cli_drift(page: str) -> str | None:
    return None if page == reference.cli_reference() else \
        f"docs/cli.md differs from the parser: {CLI_FIX}"


def test_section_7_is_what_the_settings_classes_render() -> None:
    assert settings_drift(PAGE) is None, settings_drift(PAGE)


def test_section_2_is_what_the_modules_docstrings_render() -> None:
    assert modules_drift(PAGE) is None, modules_drift(PAGE)


def test_cli_md_is_what_the_parser_renders() -> None:
    assert cli_drift(CLI_PAGE) is None, cli_drift(CLI_PAGE)


def test_a_changed_description_fails_the_settings_check(monkeypatch: pytest.MonkeyPatch) -> None:
    knob = EmbeddingAdapt.model_fields["drift_significance"]
    monkeypatch.setattr(knob, "description", "a meaning nobody reviewed")
    said = settings_drift(PAGE)
    assert said is not None and "python -m tools.reference settings --write" in said
    assert "`drift_significance` 1e-7 (a meaning nobody reviewed)" in \
        reference.settings_reference()


def test_a_changed_page_fails_the_settings_check() -> None:
    drifted = PAGE.replace("| `AESOP_CONTROL_METHOD` | `aesop` |",
                           "| `AESOP_CONTROL_METHOD` | `naive` |")
    assert drifted != PAGE
    assert settings_drift(drifted) is not None


def test_a_changed_docstring_fails_the_modules_check(monkeypatch: pytest.MonkeyPatch) -> None:
    drift = ROOT / "services" / "embedding" / "detector" / "drift.py"
    read = reference.docstring

    def docstring(path: Path) -> str | None:
        return "A meaning nobody reviewed.\n\nThe rest." if path == drift else read(path)

    monkeypatch.setattr(reference, "docstring", docstring)
    said = modules_drift(PAGE)
    assert said is not None and "python -m tools.reference modules --write" in said
    assert "\n      drift.py         A meaning nobody reviewed\n" in reference.modules_reference()


def test_a_module_without_a_docstring_still_has_its_row(monkeypatch: pytest.MonkeyPatch) -> None:
    drift = ROOT / "services" / "embedding" / "detector" / "drift.py"
    read = reference.docstring
    monkeypatch.setattr(reference, "docstring", lambda path: None if path == drift else read(path))
    assert "\n      drift.py\n      errors.py " in reference.modules_reference()


@pytest.mark.parametrize(("doc", "line"), [
    ("Scores over a cache (paper Sec. IV-A).\n\nMore.", "Scores over a cache (paper Sec. IV-A)"),
    ("The picture of one flight, aggregated\nfrom the bus. Pure: no I/O.", "The picture of one "
     "flight, aggregated from the bus"),
    ("Its routes are in :mod:`.routes`, ``/healthz`` from :func:`~.http.service_app`.",
     "Its routes are in `.routes`, `/healthz` from `.http.service_app`"),
    ("``aesop bench fairness``: one robot floods; does another keep up? It counts.",
     "`aesop bench fairness`: one robot floods; does another keep up?"),
    ("The selection of Y, eq. 3's MPC (``a. B``).", "The selection of Y, eq. 3's MPC (`a. B`)"),
    (None, ""),
])
def test_a_module_is_listed_by_its_docstrings_first_sentence(doc: str | None, line: str) -> None:
    assert reference.summary(doc) == line


def test_the_module_list_is_a_tree_that_fits_the_page() -> None:
    lines = reference.modules_reference().splitlines()
    assert lines[0] == lines[-1] == "```" and max(map(len, lines)) <= reference.LIST_WIDTH
    assert [line.split()[0] for line in lines if line[:1].isalpha()] == \
        ["shared/", "services/", "tools/"]
    services = [name for depth, name, _ in reference.rows(ROOT / "services") if depth == 1]
    assert services == ["embedding/", "reasoner/", "control/", "sim/", "ros2/", "dashboard/"]
    # a service's core folders by floor, then its own modules (the shell)
    embedding = [name for depth, name, _ in reference.rows(ROOT / "services" / "embedding")
                 if depth == 1]
    shell = embedding.index("the shell:")
    assert embedding[:shell + 1] == ["detector/", "models/", "storage/", "fleet/", "the shell:"]
    assert embedding[shell + 1:] and all(name.endswith(".py") for name in embedding[shell + 1:])
    # a row's description starts at one column, and what does not fit goes on under it
    column = len(lines[1]) - len(lines[1].removeprefix("shared/").lstrip())
    assert all(line[column - 2:column].strip() == "" and line[column:column + 1] != " "
               for line in lines[1:-1])


def test_the_references_write_their_place_and_say_when_a_page_differs(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    page = tmp_path / "architecture.md"
    page.write_text(PAGE.replace("      drift.py         Drift:", "      drift.py         Dirft:"))
    monkeypatch.setattr(reference, "ARCHITECTURE", page)
    assert reference.main(["modules"]) == 1
    assert "run python -m tools.reference modules --write" in capsys.readouterr().err
    assert reference.main(["modules", "--write"]) == 0
    assert page.read_text() == PAGE
    assert reference.main(["modules"]) == 0
    assert "section 2 is up to date" in capsys.readouterr().err


def test_a_changed_help_fails_the_cli_check() -> None:
    drifted = CLI_PAGE.replace("| ticks per flight (default 60) |", "| ticks (default 60) |")
    assert drifted != CLI_PAGE
    said = cli_drift(drifted)
    assert said is not None and "python -m tools.reference cli --write" in said


def test_writing_puts_the_text_between_the_markers_and_keeps_the_rest() -> None:
    page = f"intro\n\n{reference.BEGIN}\nold table\n{reference.END}\n\nafter\n"
    written = reference.with_settings(page, "| new |\n")
    assert written == f"intro\n\n{reference.BEGIN}\n\n| new |\n\n{reference.END}\n\nafter\n"
    assert reference.settings_in(written) == "| new |\n"
    with pytest.raises(ValueError, match="generated"):
        reference.settings_in("a page without markers")
    # the two blocks of one page share the end marker; each write keeps the other block
    both = f"{reference.MODULES_BEGIN}\nold list\n{reference.END}\n\n{page}"
    written = reference.with_settings(reference.with_modules(both, "list\n"), "| new |\n")
    assert reference.modules_in(written) == "list\n"
    assert reference.settings_in(written) == "| new |\n"


def test_every_setting_has_a_description() -> None:
    """An operator's every variable and knob has a meaning to render (the generator refuses
    one without)."""
    missing = []
    for _, classes, _ in reference.sections():
        for cls in classes:
            for name in reference.fields(cls):
                info = cls.model_fields[name]
                if not info.description:
                    missing.append(f"{cls.__name__}.{name}")
                group = info.annotation
                if isinstance(group, type) and issubclass(group, BaseModel):
                    missing += [f"{group.__name__}.{knob}" for knob, sub
                                in group.model_fields.items() if not sub.description]
    assert missing == []


def test_the_tables_name_the_variables_as_the_classes_read_them() -> None:
    text = reference.settings_reference()
    assert "| `AESOP_ROBOT` | `robot0` |" in text  # a shared field names its variable
    assert "| `AESOP_EMBEDDING_PORT` | 8001 |" in text  # env_prefix + the field's name
    assert "| `AESOP_EMBEDDING_MAX_BODY_BYTES` | 67108864 |" in text  # its own default
    assert "| `AESOP_REASONER_LLM_API_KEY`, else `OPENAI_API_KEY` | none |" in text
    assert "| `AESOP_REASONER_LLM_API_KEY_FILE` | none |" in text
    assert "| `AESOP_FAKE_LLM_PROFILE` | `fixed` |" in text
    assert "`AESOP_EMBEDDING_ADAPT` | see the knobs | drift and re-learning (section 1a): " \
           "`recalibrate` `window` (" in text
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    assert len(rows) == len({line.split(" | ")[0] for line in rows})  # each variable once
    # every field of every table is a row: the fake's knobs and its host, port and limit
    fake = [line for line in rows if line.startswith("| `AESOP_FAKE_LLM_")]
    assert len(fake) == len(FakeLLMSettings.model_fields) + 3
    assert "`AESOP_EMBEDDING_LIMITS`" in text and "limits" in EmbeddingSettings.model_fields


def test_the_cli_reference_has_every_command_and_argument() -> None:
    import argparse

    from tools.cli import build_parser

    text = reference.cli_reference()
    assert text.startswith("# `aesop`") and reference.CLI_HEADER in text
    for path, parser, _ in reference.commands(build_parser()):
        assert f"\n## `{' '.join(path)}`\n" in text
        for action in parser._actions:
            if action.option_strings and not isinstance(action, argparse._HelpAction):
                assert f"| `{', '.join(action.option_strings)}` |" in text
    # a default that is this machine's is shown as the help says it
    assert "| `--workers` | `WORKERS` | every CPU |" in text
    assert "## `aesop serve fake-llm`" in text and "| `--profile` |" in text
