"""The headless Chromium the studio's tests drive (Debian's, never a downloaded one).

A pytest plugin (tests/conftest.py lists it): fixtures `browser`, `studio` (a fresh page of
the studio against the `client` fixture's Serve app) and `shots` (where screenshots go); a test
using `browser` is marked `browser`.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.support.needs import missing, need_module
from tests.support.studio_page import CHROMIUM, CHROMIUM_ARGS, Studio, open_studio


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """One headless Chromium for the module (never a downloaded browser)."""
    sync_api = need_module("playwright.sync_api", "pip install playwright (the test extra)")
    if not Path(CHROMIUM).is_file():
        missing(f"no Chromium at {CHROMIUM}: apt-get install -y chromium (or set LINKS_CHROMIUM)")
    sync_playwright = sync_api.sync_playwright
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()


@pytest.fixture
def studio(browser: Any, client: Any) -> Iterator[Studio]:
    """A fresh browser context on the studio; fails the test if the page logged any error."""
    with open_studio(browser, client.port) as page:
        yield page


@pytest.fixture
def shots(tmp_path: Path) -> Path:
    """Where screenshots go: LINKS_STUDIO_SCREENSHOTS, else this test's temporary folder."""
    folder = Path(os.environ.get("LINKS_STUDIO_SCREENSHOTS") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)
    return folder
