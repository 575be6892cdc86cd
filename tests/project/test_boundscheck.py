"""The kernel tests again, with numba checking every index (NUMBA_BOUNDSCHECK=1).

numba checks no bounds by default: a kernel given a buffer too small for what it writes
corrupts memory silently, and the process may crash much later, elsewhere. The kernels'
entry points check their buffers' shapes (engine.buffers.check_buffer); this pass catches what those
checks cannot see, a kernel indexing past a buffer it made itself or one whose shape was
right and whose contents were not. It runs the engine's, refinement's and the search
kernels' tests in a process of their own (the setting is read when numba is imported), with
their compiled code cached apart from the package's (.pytest_cache/d/numba-boundscheck/KEY,
KEY a digest of the kernels' sources). By hand:

    NUMBA_BOUNDSCHECK=1 NUMBA_CACHE_DIR=/tmp/links-boundscheck \\
        python -m pytest -q -p no:cacheprovider -p tests.support.boundscheck <files of KERNEL_TESTS>
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numba
import pytest

ROOT = Path(__file__).resolve().parents[2]

#: Every test file that calls a kernel with buffers it made, and those of the engine,
#: refinement and retrieval kernels besides; tests.support.boundscheck leaves out the tests that
#: need S3 or Ray.
KERNEL_TESTS = (
    "tests/engine/test_kernel_buffers.py",
    "tests/engine/test_turning.py",
    "tests/engine/test_solver.py",
    "tests/engine/test_simulate_calls.py",
    "tests/engine/test_sampling.py",
    "tests/engine/test_transmission.py",
    "tests/engine/test_topology.py",
    "tests/engine/test_solution_path.py",
    "tests/engine/test_reduce.py",
    "tests/engine/test_validation.py",
    "tests/engine/test_paths.py",
    "tests/engine/test_refine.py",
    "tests/engine/test_synthesis.py",
    "tests/engine/test_collisions.py",
    "tests/search/test_retrieval.py",
    "tests/release/test_release_scan.py",
)
#: Fewer passing tests than this means the pass ran far less than it should.
MIN_PASSED = 400


def kernel_sources_key() -> str:
    """A digest of every module of the package that compiles kernels, and of numba's
    version. numba keys a cached kernel on its own file only, but a kernel calling another
    module's carries a copy of it: a cache kept across an edit of the callee would run the
    old callee unnoticed."""
    digest = hashlib.sha256(numba.__version__.encode())
    package = ROOT / "links_ray"
    for path in sorted(package.rglob("*.py")):
        source = path.read_bytes()
        if b"njit" in source:
            digest.update(path.relative_to(package).as_posix().encode() + b"\0" + source)
    return digest.hexdigest()[:16]


def boundscheck_cache(config: pytest.Config, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where the pass's compiled kernels are kept: in pytest's cache under the kernels'
    `kernel_sources_key`, so later runs of the same code load them (older keys' folders are
    removed), or for this session alone when pytest keeps no cache."""
    cache = getattr(config, "cache", None)
    if cache is None:
        return tmp_path_factory.mktemp("numba-boundscheck")
    root = Path(cache.mkdir("numba-boundscheck"))
    key = kernel_sources_key()
    for old in root.iterdir():
        if old.name != key:
            shutil.rmtree(old, ignore_errors=True)
    (root / key).mkdir(exist_ok=True)
    return root / key


def run_bound_checked(files: tuple[str, ...], cache: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "NUMBA_BOUNDSCHECK": "1", "NUMBA_CACHE_DIR": str(cache)}
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    return subprocess.run(
        [*command, "-p", "tests.support.boundscheck", *files],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=3600,
    )


def passed(output: str) -> int:
    found = re.search(r"(\d+) passed", output)
    return int(found.group(1)) if found else 0


def test_the_kernel_tests_pass_with_bounds_checked(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> None:
    run = run_bound_checked(KERNEL_TESTS, boundscheck_cache(request.config, tmp_path_factory))
    tail = "\n".join(run.stdout.splitlines()[-60:] + run.stderr.splitlines()[-20:])
    print(run.stdout.splitlines()[-1] if run.stdout else "")  # its summary, with -s or -rP
    assert run.returncode == 0, f"the bound-checked pass failed:\n{tail}"
    assert passed(run.stdout) >= MIN_PASSED, f"the bound-checked pass ran too little:\n{tail}"
