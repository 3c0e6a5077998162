"""Issue 44: every shell block of the README, docs/ and deploy/README.md that is marked
runnable is run as a reader would run it from the repository's root, and must end with the
status its marker says. (``test_docs_commands.py`` checks every ``aesop`` command against the
command tree; this runs the ones that can run on their own.)

A marker is an HTML comment, which GitHub does not show, on the line right before the
opening fence of a ``sh`` or ``bash`` block::

    <!-- runnable -->            the block exits 0
    <!-- runnable: exit 2 -->    the block exits 2 (a usage error the docs show)

Each block runs under ``bash -e -o pipefail`` (every command of it counts, not only the last)
in a fresh folder laid out as the repository's root: copies of ``docker-compose.yml`` and
``deploy/`` (not its secrets), ``.venv`` a link to this Python's environment, whose ``aesop``
comes first on PATH; HOME is a folder of its own, and no ``AESOP_*``, ``ZENOH_*`` or ``RMW_*``
variable comes from the environment the tests run in. So a block may write where the docs
say (``deploy/tls``, ``aesop-data``) without touching the checkout. A block to mark is
self-contained and quick: no stack, no fixed port, no sudo, no network.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FILES = sorted([ROOT / "README.md", ROOT / "deploy" / "README.md",
                *(ROOT / "docs").glob("*.md")])
MARKER = re.compile(r"<!--\s*runnable(?::\s*exit\s+(\d+))?\s*-->")
FENCE = re.compile(r"```(sh|bash)")
BLOCK_TIMEOUT_S = 120  # a block that hangs fails here
FOREIGN = ("AESOP_", "ZENOH_", "RMW_")  # the caller's settings stay out of a block's run


@dataclass(frozen=True)
class Block:
    path: Path
    line: int  # the opening fence's, 1-based
    status: int  # the exit status its marker says
    code: str

    @property
    def where(self) -> str:
        shown = self.path.relative_to(ROOT) if self.path.is_relative_to(ROOT) else self.path
        return f"{shown}:{self.line}"


def runnable_blocks(path: Path) -> list[Block]:
    """The marked blocks of ``path``; a marker that is misspelt or not right above a
    ``sh``/``bash`` fence is an error naming its line (else its block would silently not
    run)."""
    lines = path.read_text().splitlines()
    blocks = []
    for i, line in enumerate(lines):
        if not (line.lstrip().startswith("<!--") and "runnable" in line.lower()):
            continue
        marker = MARKER.fullmatch(line.strip())
        if marker is None:
            raise ValueError(f"{path}:{i + 1}: not a runnable marker: {line.strip()!r} "
                             "(<!-- runnable --> or <!-- runnable: exit N -->)")
        if i + 1 >= len(lines) or not FENCE.fullmatch(lines[i + 1].strip()):
            raise ValueError(f"{path}:{i + 1}: a runnable marker must be right above a "
                             "```sh or ```bash fence")
        end = next((j for j in range(i + 2, len(lines)) if lines[j].strip() == "```"), None)
        if end is None:
            raise ValueError(f"{path}:{i + 2}: the block never closes")
        blocks.append(Block(path, i + 2, int(marker.group(1) or 0),
                            "\n".join(lines[i + 2:end]) + "\n"))
    return blocks


def repository_root_like(folder: Path) -> Path:
    """``folder`` laid out as the repository's root for a block to run in."""
    folder.mkdir(parents=True)
    shutil.copy(ROOT / "docker-compose.yml", folder / "docker-compose.yml")
    shutil.copytree(ROOT / "deploy", folder / "deploy",
                    ignore=shutil.ignore_patterns("secrets", "__pycache__"))
    (folder / ".venv").symlink_to(sys.prefix, target_is_directory=True)
    (folder / "home").mkdir()
    return folder


def run(block: Block, folder: Path) -> str | None:
    """Run ``block`` in ``folder`` (as :func:`repository_root_like` left it): None if it
    ends as its marker says, else what happened."""
    venv_bin = Path(sys.prefix) / "bin"
    assert (venv_bin / "aesop").exists(), f"no aesop in {venv_bin}: is the project installed?"
    env = {k: v for k, v in os.environ.items() if not k.startswith(FOREIGN)}
    env |= {"HOME": str(folder / "home"),
            "PATH": os.pathsep.join([str(venv_bin), env.get("PATH", "/usr/bin:/bin")])}
    try:
        done = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", block.code], cwd=folder,
                              env=env, capture_output=True, text=True,
                              stdin=subprocess.DEVNULL, timeout=BLOCK_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return f"{block.where}: still running after {BLOCK_TIMEOUT_S} s"
    if done.returncode == block.status:
        return None
    return (f"{block.where}: exit {done.returncode}, the docs say {block.status}\n"
            f"{block.code}--- stdout\n{done.stdout[-2000:]}--- stderr\n{done.stderr[-2000:]}")


BLOCKS = [block for path in FILES for block in runnable_blocks(path)]


@pytest.mark.parametrize("block", BLOCKS, ids=lambda b: b.where)
def test_a_runnable_block_exits_as_the_docs_say(block: Block, tmp_path: Path) -> None:
    assert run(block, repository_root_like(tmp_path / "root")) is None


def test_the_docs_mark_their_self_contained_blocks() -> None:
    # a marker the parser stopped finding would leave this test with nothing to run
    assert len(BLOCKS) >= 4, [b.where for b in BLOCKS]


SELF_TEST = """\
A block that fails is reported:

<!-- runnable -->
```sh
aesop zenoh certs   # no DIR: a usage error (exit 2), but marked as exiting 0
```

A usage error the docs show with its status:

<!-- runnable: exit 2 -->
```sh
aesop zenoh certs
```

Every command counts, not only the last:

<!-- runnable -->
```bash
false
echo fine
```

<!-- runnable -->
```sh
aesop --version > version.txt
grep -q "^aesop " version.txt
```
"""


def test_a_failing_block_is_reported_with_its_line(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text(SELF_TEST)
    blocks = runnable_blocks(page)
    assert [(b.line, b.status) for b in blocks] == [(4, 0), (11, 2), (18, 0), (24, 0)]
    said = [run(b, repository_root_like(tmp_path / f"root{b.line}")) for b in blocks]
    assert said[0] is not None and said[0].startswith(f"{page}:4: exit 2, the docs say 0")
    assert "aesop zenoh certs" in said[0]  # the block and its stderr are shown
    assert said[1] is None
    assert said[2] is not None and said[2].startswith(f"{page}:18: exit 1, the docs say 0")
    assert said[3] is None


@pytest.mark.parametrize("text", ["<!-- runnable: exit two -->\n```sh\ntrue\n```\n",
                                  "<!-- runnable -->\n\n```sh\ntrue\n```\n",
                                  "<!-- runnable -->\n```python\nprint()\n```\n",
                                  "<!-- runnable -->\n```sh\ntrue\n",
                                  "<!-- Runnable -->\n```sh\ntrue\n```\n"])
def test_a_marker_that_would_run_nothing_is_an_error(text: str, tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text(text)
    with pytest.raises(ValueError, match=r"page\.md:\d+: "):
        runnable_blocks(page)
