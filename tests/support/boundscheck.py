"""A pytest plugin for the bound-checked pass of the kernel tests (tests/project/test_boundscheck.py
runs them in a process of its own with `-p tests.support.boundscheck`).

It refuses to run unless numba checks bounds in this process and caches what it compiles
outside the package (a bound-checked build in the package's `__pycache__` would be loaded by
every later run: numba's cache key leaves the setting out), and deselects the tests that need
Ray or S3: the pass is about the kernels, and the whole suite runs those tests anyway.
"""

from __future__ import annotations

import os
from pathlib import Path

import numba
import numpy as np
import pytest
from numba.core import config as numba_config

#: Fixtures whose tests the pass leaves out: they start SeaweedFS (and Ray on top of it), or
#: read a generated dataset (tests/engine makes its own without Ray: generating it again with
#: every index checked would cost minutes, and the tests that read it run in the suite anyway).
NEEDS_SERVICES = ("s3_server", "dataset")
PACKAGE = Path(__file__).resolve().parents[2] / "links_ray"


def _write_past_end(buffer: np.ndarray) -> None:
    buffer[buffer.shape[0]] = 1.0


def pytest_configure(config: pytest.Config) -> None:
    if numba_config.BOUNDSCHECK != 1:
        raise pytest.UsageError("tests.support.boundscheck: run with NUMBA_BOUNDSCHECK=1")
    cache = os.environ.get("NUMBA_CACHE_DIR", "")
    if not cache or Path(cache).resolve().is_relative_to(PACKAGE):
        raise pytest.UsageError(
            "tests.support.boundscheck: set NUMBA_CACHE_DIR to a folder outside links_ray, "
            f"got {cache!r}"
        )
    # The setting is read once, when numba is imported: prove it took.
    try:
        numba.njit(cache=False)(_write_past_end)(np.zeros(2))
    except IndexError:
        return
    raise pytest.UsageError("tests.support.boundscheck: numba wrote past an array's end unchecked")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    kept, left = [], []
    for item in items:
        needs = any(name in getattr(item, "fixturenames", ()) for name in NEEDS_SERVICES)
        (left if needs else kept).append(item)
    if left:
        config.hook.pytest_deselected(items=left)
        items[:] = kept
