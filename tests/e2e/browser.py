"""What the browser tests share: Debian's chromium, its flags, a module-scoped browser
(``browser`` fixture in ``conftest.py``), screenshots and the page's canvas hooks."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from playwright.sync_api import Page

CHROMIUM = "/usr/bin/chromium"  # Debian's package; `make browser` (and `make test`) installs it
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--no-first-run"]


def screenshot(page: Page, tmp_path: Path, name: str) -> Path:
    path = tmp_path / name
    page.screenshot(path=str(path))
    out = os.environ.get("AESOP_SCREENSHOT_DIR")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        shutil.copy(path, Path(out) / name)
    return path


def canvas_count(page: Page, canvas: str, attr: str) -> int:
    return int(page.get_attribute(f"#{canvas}", f"data-{attr}") or 0)
