"""The admin token ``aesop up`` generates is kept in a file only its owner reads (issue 14)."""

from __future__ import annotations

import stat
from pathlib import Path

from tools.stack.up import write_token


def mode(path: Path) -> int:
    return stat.S_IMODE(path.lstat().st_mode)


def test_a_new_token_file_is_0600(tmp_path: Path) -> None:
    path = write_token(tmp_path, "a" * 32)
    assert path.read_text() == "a" * 32 + "\n" and mode(path) == 0o600


def test_an_existing_readable_file_becomes_0600(tmp_path: Path) -> None:
    (tmp_path / "admin-token").write_text("old\n")
    (tmp_path / "admin-token").chmod(0o644)
    path = write_token(tmp_path, "b" * 32)
    assert path.read_text() == "b" * 32 + "\n" and mode(path) == 0o600


def test_a_symlink_in_its_place_is_replaced_not_followed(tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere.txt"
    elsewhere.write_text("not yours\n")
    elsewhere.chmod(0o644)
    data = tmp_path / "data"
    data.mkdir()
    (data / "admin-token").symlink_to(elsewhere)
    path = write_token(data, "c" * 32)
    assert elsewhere.read_text() == "not yours\n" and mode(elsewhere) == 0o644
    assert not path.is_symlink() and path.read_text() == "c" * 32 + "\n"
    assert mode(path) == 0o600
