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


class _SharedBrowser:
    """The Chromium the `browser` fixture hands to one test module after another: launched when
    a module first asks for it, closed before the first test of a module none of whose tests
    use it, and at the session's end. One launch serves every module in a row that asks (the
    studio's test_studio_*.py files), not one a module. It is not kept for the whole session:
    while Playwright runs, its event loop is the main thread's running loop, and a test's
    `asyncio.run` would fail."""

    playwright: Any = None  # the started `sync_playwright()`
    chromium: Any = None
    #: The test files (node id paths) of the session holding a test that uses `browser`.
    modules: frozenset[str] = frozenset()


_SHARED = _SharedBrowser()


def _module(item: pytest.Item) -> str:
    return item.nodeid.split("::")[0]


def _launch() -> Any:
    """Start Playwright and launch Chromium in it, held in `_SHARED`."""
    sync_api = need_module("playwright.sync_api", "pip install playwright (the test extra)")
    if not Path(CHROMIUM).is_file():
        missing(f"no Chromium at {CHROMIUM}: apt-get install -y chromium (or set LINKS_CHROMIUM)")
    playwright = sync_api.sync_playwright().start()
    try:
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
    except BaseException:
        playwright.stop()
        raise
    _SHARED.playwright, _SHARED.chromium = playwright, chromium
    return chromium


def _close() -> None:
    """Close the shared Chromium and stop its Playwright, if they run."""
    playwright, chromium = _SHARED.playwright, _SHARED.chromium
    if playwright is None:
        return
    _SHARED.playwright = _SHARED.chromium = None
    try:
        chromium.close()
    finally:
        playwright.stop()


def pytest_collection_finish(session: pytest.Session) -> None:
    _SHARED.modules = frozenset(
        _module(item) for item in session.items if "browser" in getattr(item, "fixturenames", ())
    )


def pytest_runtest_setup(item: pytest.Item) -> None:
    if _SHARED.chromium is not None and _module(item) not in _SHARED.modules:
        _close()


@pytest.fixture(scope="session")
def shared_browser() -> Iterator[_SharedBrowser]:
    """The session's holder of the `browser` fixture's Chromium; closes it at the end."""
    yield _SHARED
    _close()


@pytest.fixture(scope="module")
def browser(shared_browser: _SharedBrowser) -> Any:
    """A headless Chromium (never a downloaded browser), shared by the modules in a row that
    ask for it (`_SharedBrowser`); launched again if it went away."""
    if shared_browser.chromium is not None and not shared_browser.chromium.is_connected():
        _close()
    return shared_browser.chromium or _launch()


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
