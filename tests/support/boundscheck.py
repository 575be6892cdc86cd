"""A pytest plugin that runs tests with numba checking every index (NUMBA_BOUNDSCHECK=1).

    python -m pytest -p tests.support.boundscheck tests/engine

numba checks no bounds by default: a kernel given a buffer too small for what it writes
corrupts memory silently, and the process may crash much later, elsewhere. The kernels' entry
points check their buffers' shapes (engine.buffers.check_buffer); bound-checked runs catch what
those checks cannot see, a kernel indexing past a buffer it made itself or one whose shape was
right and whose contents were not. tests/run runs the engine's tests this way (their only run
there), and tests/project/test_boundscheck.py runs the other kernel tests this way.

numba reads the setting once, when it is imported, so the plugin sets it when it loads, before
any test module imports numba (a `-p` plugin loads first; pytest-xdist's workers inherit the
variables). numba's cache key leaves the setting out, so the bound-checked code is cached
apart from the package's `__pycache__` (which every later process would load, unchecked code
loading into a checked run and the reverse): under `.cache/numba-boundscheck/KEY` in the
repository, KEY a digest of the kernels' sources and numba's version, older keys removed; or
where NUMBA_CACHE_DIR says, when it is set outside the package.

The tests that need Ray or S3 are deselected: the pass is about the kernels, and the suite runs
those tests in its other steps.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "links_ray"
#: Fixtures whose tests the pass leaves out: the session's Ray and the S3 server.
NEEDS_SERVICES = ("ray_cluster", "s3_server", "restartable_s3_server", "s3_env")


def kernel_sources_key() -> str:
    """A digest of every module of the package that compiles kernels, and of numba's version.
    numba keys a cached kernel on its own file only, but a kernel calling another module's
    carries a copy of it: a cache kept across an edit of the callee would run the old callee."""
    digest = hashlib.sha256(version("numba").encode())
    for path in sorted(PACKAGE.rglob("*.py")):
        source = path.read_bytes()
        if b"njit" in source:
            digest.update(path.relative_to(PACKAGE).as_posix().encode() + b"\0" + source)
    return digest.hexdigest()[:16]


def default_cache() -> Path:
    """`.cache/numba-boundscheck/KEY` in the repository; the folders of other keys removed."""
    root = ROOT / ".cache" / "numba-boundscheck"
    key = kernel_sources_key()
    root.mkdir(parents=True, exist_ok=True)
    for old in root.iterdir():
        if old.name != key:
            shutil.rmtree(old, ignore_errors=True)
    (root / key).mkdir(exist_ok=True)
    return root / key


def _set_up_environment() -> None:
    if "numba" in sys.modules:
        return  # too late to set anything: pytest_configure says whether it took
    os.environ["NUMBA_BOUNDSCHECK"] = "1"
    if not os.environ.get("NUMBA_CACHE_DIR"):
        os.environ["NUMBA_CACHE_DIR"] = str(default_cache())


_set_up_environment()

import numba  # noqa: E402  (after the environment above: numba reads it on import)
import numpy as np  # noqa: E402
from numba.core import config as numba_config  # noqa: E402


def _write_past_end(buffer: np.ndarray) -> None:
    buffer[buffer.shape[0]] = 1.0


def pytest_configure(config: pytest.Config) -> None:
    if numba_config.BOUNDSCHECK != 1:
        raise pytest.UsageError(
            "tests.support.boundscheck: numba was imported before the plugin loaded, with "
            "bounds unchecked (load it with -p, or set NUMBA_BOUNDSCHECK=1)"
        )
    cache = os.environ.get("NUMBA_CACHE_DIR", "")
    if not cache or Path(cache).resolve().is_relative_to(PACKAGE):
        raise pytest.UsageError(
            "tests.support.boundscheck: set NUMBA_CACHE_DIR to a folder outside links_ray, "
            f"got {cache!r}"
        )
    # Prove that the setting took in this process.
    try:
        numba.njit(cache=False)(_write_past_end)(np.zeros(2))
    except IndexError:
        return
    raise pytest.UsageError("tests.support.boundscheck: numba wrote past an array's end unchecked")


def pytest_report_header() -> str:
    return f"numba checks bounds (tests.support.boundscheck), cache {os.environ['NUMBA_CACHE_DIR']}"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    kept, left = [], []
    for item in items:
        needs = any(name in getattr(item, "fixturenames", ()) for name in NEEDS_SERVICES)
        (left if needs else kept).append(item)
    if left:
        config.hook.pytest_deselected(items=left)
        items[:] = kept
