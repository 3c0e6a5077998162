"""Issue 44: the docs said commands the CLI did not take. Every ``aesop`` command in the
README, docs/ and deploy/README.md (code blocks and inline code) is checked against the
command tree itself: its subcommands exist and each of its flags is one that subcommand
takes. (Those in shell blocks marked runnable are also run: test_docs_runnable.py.)"""

from __future__ import annotations

import argparse
import re
import shlex
from collections.abc import Iterator
from pathlib import Path

import pytest

from tools import cli
from tools.fakes.llm import build_parser as fake_llm_parser

ROOT = Path(__file__).resolve().parents[2]
FILES = sorted([ROOT / "README.md", ROOT / "deploy" / "README.md",
                *(ROOT / "docs").glob("*.md")])
FENCE = re.compile(r"```[a-z0-9]*\n(.*?)```", re.S)
INLINE = re.compile(r"`([^`\n]+)`")
STOP = {"|", "||", "&&", ";", ">", ">>", "2>", "2>&1", "&", "#"}


def commands(text: str) -> Iterator[tuple[str, bool]]:
    """Each command line that runs ``aesop`` (the part from it on), and whether it is in a
    code block (else inline code)."""
    for block in FENCE.findall(text):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" #", 1)[0]
            for part in re.split(r"&&|;|\|", line):
                yield from _from(part, True)
    prose = FENCE.sub("", text)
    for span in INLINE.findall(prose):
        yield from _from(span, False)


def _from(part: str, block: bool) -> Iterator[tuple[str, bool]]:
    match = re.search(r"(?:^|\s|/)aesop\s+(-{0,2}[a-z][^\s]*.*)$", part)
    if match:
        yield match.group(1).strip(), block


def problems(command: str, block: bool, parser: argparse.ArgumentParser) -> list[str]:
    try:
        words = shlex.split(command)
    except ValueError:
        words = command.split()
    said: list[str] = []
    path = ["aesop"]
    for i, word in enumerate(words):
        if word in STOP or word.startswith(("$", "<", ">")) or "..." in word:
            break
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if subs and not word.startswith("-"):
            choices = subs[0].choices
            if word in choices:
                parser, path = choices[word], [*path, word]
                continue
            bare = word.strip("):,.;'\"[]")
            if bare in choices:  # prose around it: "aesop up): ..."
                parser, path = choices[bare], [*path, bare]
                continue
            if block and re.fullmatch(r"[a-z][a-z0-9-]*", word) and i == len(path) - 1:
                said.append(f"{' '.join(path)} has no subcommand {word!r}")
            break
        if word == "fake-llm" and path == ["aesop", "serve"]:
            parser = fake_llm_parser()  # the fake takes flags of its own (see its --help)
        if word.startswith("--"):
            flag = word.split("=", 1)[0].strip("`.,;:)")
            if flag not in parser._option_string_actions:
                said.append(f"{' '.join(path)} takes no {flag}")
    return said


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_aesop_command_in_the_docs_is_one_the_cli_takes(path: Path) -> None:
    parser = cli.build_parser()
    found = list(commands(path.read_text()))
    wrong = [f"`aesop {command}`: {problem}" for command, block in found
             for problem in problems(command, block, parser)]
    assert wrong == []


def test_the_check_finds_a_wrong_flag_and_a_wrong_subcommand() -> None:
    parser = cli.build_parser()
    text = ("```sh\n.venv/bin/aesop up --random-ports --no-such-flag\naesop bench nothing\n"
            "aesop demo --attach \\\n  --vehicle bus   # fine\n```\n"
            "and inline `aesop watch --robot all`, `aesop up): prose`.\n")
    found = list(commands(text))
    assert [c for c, _ in found] == ["up --random-ports --no-such-flag", "bench nothing",
                                     "demo --attach    --vehicle bus", "watch --robot all",
                                     "up): prose"]
    said = [p for command, block in found for p in problems(command, block, parser)]
    assert said == ["aesop up takes no --no-such-flag",
                    "aesop bench has no subcommand 'nothing'"]
    total = sum(len(list(commands(f.read_text()))) for f in FILES)
    assert total > 100  # the docs' commands are all found
