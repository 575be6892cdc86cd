"""The kernel tests outside tests/engine run again with numba checking every index, and
tests/run runs the engine's own tests that way (tests/support/boundscheck.py says why).

This pass runs the search kernels' and the release scanner's tests in a process of their own
(the setting is read when numba is imported), with their compiled code cached apart from the
package's (the plugin's `.cache/numba-boundscheck/KEY`, which tests/run's engine step has
mostly filled). By hand:

    python -m pytest -q -p no:cacheprovider -p tests.support.boundscheck <files of KERNEL_TESTS>
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: The test files outside tests/engine that call kernels with buffers they made: the search
#: kernels' and the release scanner's. The plugin leaves out the tests that need S3 or Ray.
KERNEL_TESTS = ("tests/search/test_retrieval.py", "tests/release/test_release_scan.py")
#: Fewer passing tests than this means the pass ran far less than it should.
MIN_PASSED = 60


def run_bound_checked(files: tuple[str, ...]) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    return subprocess.run(
        [*command, "-p", "tests.support.boundscheck", *files],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=3600,
    )


def passed(output: str) -> int:
    found = re.search(r"(\d+) passed", output)
    return int(found.group(1)) if found else 0


def test_the_kernel_tests_pass_with_bounds_checked() -> None:
    run = run_bound_checked(KERNEL_TESTS)
    tail = "\n".join(run.stdout.splitlines()[-60:] + run.stderr.splitlines()[-20:])
    print(run.stdout.splitlines()[-1] if run.stdout else "")  # its summary, with -s or -rP
    assert run.returncode == 0, f"the bound-checked pass failed:\n{tail}"
    assert passed(run.stdout) >= MIN_PASSED, f"the bound-checked pass ran too little:\n{tail}"


def pytest_lines(script: str) -> list[list[str]]:
    """The words of each `python -m pytest` command in a shell script, its lines joined."""
    joined = script.replace("\\\n", " ")
    return [shlex.split(line.split("||")[0]) for line in joined.splitlines() if "-m pytest" in line]


def test_tests_run_checks_bounds_in_the_engines_step_alone() -> None:
    """tests/run's engine step is the engine's only run there: it loads the plugin. No other
    step does (their kernels would compile bound-checked into the package's cache)."""
    commands = pytest_lines((ROOT / "tests" / "run").read_text())
    engine = [
        words
        for words in commands
        if "tests/engine" in words and "--ignore=tests/engine" not in words
    ]
    assert len(engine) == 1, commands
    assert "tests.support.boundscheck" in engine[0] and "tests.support.no_ray" in engine[0]
    others = [words for words in commands if words is not engine[0]]
    assert others and all("tests.support.boundscheck" not in words for words in others)
