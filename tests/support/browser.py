"""The headless Chromium the studio's tests drive (Debian's, never a downloaded one).

A pytest plugin (tests/conftest.py lists it): fixture `browser`; a test using it is marked
`browser`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.support.needs import missing, need_module
from tests.support.studio_page import CHROMIUM, CHROMIUM_ARGS


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
