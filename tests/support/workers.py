"""Two test processes at once (pytest-xdist's `-n 2`: `tests/run` runs the engine's tests so,
and any run may): what keeps them apart.

A pytest plugin (tests/conftest.py lists it). Each xdist worker is a whole session of its own:
its own S3 server, Ray and datasets (their fixtures are per process). Two things would still
be shared through the machine, so each worker is given its own:

- Ray's temporary folder (`RAY_TMPDIR`). A plain `ray.init()` joins the cluster whose address
  is filed in that folder (`ray_current_cluster`, written by `ray start` and by
  `ray.cluster_utils.Cluster`), so with one folder a worker's Ray, or a command a test runs,
  could join the other worker's. The folder is short: Ray's socket paths live under it.
- pytest's own temporary folders are already per worker (xdist names them).

It also orders the files for the workers. tests/run's workers take whole files (`--dist
loadfile`) in the order collected (`--no-loadscope-reorder`; xdist would otherwise send the
files with the most tests first, and a long file of one test last, for one worker to run alone
while the other waits). The files in LONGEST_FIRST go first, longest first, so that the two
workers finish together.

Run alone (no xdist, or `-n 0`), the plugin does nothing.
"""

from __future__ import annotations

import os
import shutil
import tempfile

import pytest


def worker_name() -> str | None:
    """This process's xdist worker ("gw0", "gw1", ...), or None outside xdist."""
    return os.environ.get("PYTEST_XDIST_WORKER")


#: The files that hold a worker longest in tests/run's first two steps, longest first (the
#: slowest-tests lists tests/run prints say which): a cold compile of every kernel, commits raced
#: on S3, command runs, the large dataset's build.
LONGEST_FIRST = (
    "tests/cli/test_warm.py",
    "tests/data/test_commit.py",
    "tests/cli/test_export_mechanism.py",
    "tests/search/test_retrieval_scale.py",
    "tests/release/test_release_import.py",
    "tests/engine/synthesis/test_synthesis.py",
    "tests/engine/fabrication/test_collisions.py",
    "tests/engine/test_kernel_buffers.py",
    "tests/engine/kinematics/test_turning.py",
)


class _RayFolder:
    path: str | None = None


_FOLDER = _RayFolder()


def pytest_configure(config: pytest.Config) -> None:
    worker = worker_name()
    if worker is None or "RAY_TMPDIR" in os.environ:
        return
    # Before any fixture starts Ray: every Ray of this process, and of the commands its tests
    # run, keeps its files here unless a test names a folder of its own.
    _FOLDER.path = tempfile.mkdtemp(prefix=f"links-{worker}-", dir="/tmp")
    os.environ["RAY_TMPDIR"] = _FOLDER.path


def pytest_unconfigure(config: pytest.Config) -> None:
    if _FOLDER.path is not None:
        shutil.rmtree(_FOLDER.path, ignore_errors=True)
        _FOLDER.path = None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if worker_name() is None:
        return
    rank = {path: place for place, path in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))
