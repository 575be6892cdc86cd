"""What the suite does when something a test needs is missing: under CI it fails, elsewhere it
skips, saying what is missing either way.

A CI run that skipped the S3 server's or the browser's tests would pass without having run
them, so with ``CI`` set (``true``, as CI services set it, or ``1``/``yes``) a missing
dependency fails the test in one line. On a developer's machine the test is skipped and pytest's
summary (``-ra``) prints the same line.
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType
from typing import NoReturn

import pytest


def under_ci() -> bool:
    """Whether this run is a CI run (the ``CI`` variable)."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def missing(what: str) -> NoReturn:
    """Stop the calling test (or module, or fixture) for want of `what`: a one-line failure
    under CI, a skip with `what` as its reason elsewhere."""
    if under_ci():
        pytest.fail(f"{what} (CI=true: a missing test dependency fails the run)", pytrace=False)
    pytest.skip(what, allow_module_level=True)


def need_module(name: str, install: str) -> ModuleType:
    """Import `name`, or stop as `missing` says (`install`: how to get it)."""
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        why = f"cannot import {name} ({exc}): {install}"
    missing(why)  # outside the handler: the report is one line, without the ImportError


def no_skip_under_ci(report: pytest.TestReport) -> None:
    """Under CI, make a skip that did not come through `missing` (a plain ``pytest.skip``, a
    skip mark, an empty parametrization) a failure that gives its reason."""
    if not (under_ci() and report.skipped) or hasattr(report, "wasxfail"):
        return
    longrepr = report.longrepr
    reason = longrepr[2] if isinstance(longrepr, tuple) else str(longrepr)
    reason = reason.removeprefix("Skipped: ")
    report.outcome = "failed"
    report.longrepr = f"skipped under CI=true, where no test may be: {reason}"


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> pytest.TestReport:
    """The plugin's hook (tests/conftest.py lists this module): under CI nothing is skipped."""
    report = yield
    no_skip_under_ci(report)
    return report
