"""The settings and CLI references are generated from the code (issue 45: the hand-written
tables drifted): section 7 of docs/architecture.md, between its markers, is what
``settings_reference()`` renders from the settings classes, and docs/cli.md is what
``cli_reference()`` renders from the parser. Each check is shown failing on a changed
description (a check that cannot fail is a defect)."""

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


def settings_drift(page: str) -> str | None:
    """What to do when section 7's generated text is not what the code renders."""
    return None if reference.settings_in(page) == reference.settings_reference() else \
        f"docs/architecture.md section 7 differs from the settings classes: {SETTINGS_FIX}"


def cli_drift(page: str) -> str | None:
    return None if page == reference.cli_reference() else \
        f"docs/cli.md differs from the parser: {CLI_FIX}"


def test_section_7_is_what_the_settings_classes_render() -> None:
    assert settings_drift(PAGE) is None, settings_drift(PAGE)


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
