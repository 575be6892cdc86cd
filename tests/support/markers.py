"""The `ray`, `s3` and `browser` marks, set on each test from the fixtures it uses.

A pytest plugin (tests/conftest.py lists it). pyproject.toml registers the marks
(`--strict-markers`); a test gets one when its fixture closure (the fixtures it names and every
fixture those depend on) holds one of the fixtures below, so `pytest -m "not ray"` runs what
needs no Ray, and `-m "not s3 and not browser"` what needs neither the S3 server nor Chromium.
A test that starts Ray itself, without the `ray_cluster` fixture, carries `pytest.mark.ray` in
its own module.
"""

from __future__ import annotations

import pytest

#: The mark each fixture brings to every test whose closure holds it.
FIXTURE_MARKS = {
    "ray_cluster": "ray",
    "s3_server": "s3",
    "restartable_s3_server": "s3",
    "s3_env": "s3",
    "browser": "browser",
}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        closure = set(getattr(item, "fixturenames", ()))
        for fixture, mark in FIXTURE_MARKS.items():
            if fixture in closure and item.get_closest_marker(mark) is None:
                item.add_marker(getattr(pytest.mark, mark))
