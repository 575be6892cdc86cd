"""`links warm`: a first run on an empty numba cache says that it compiles; `links warm` then
compiles every command's kernels into the cache, after which no command has anything to say.

A file of its own: its cold compile is the suite's longest single test, and tests/run's
workers take whole files, so it does not hold up the other command-line tests.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


def cache_files(folder: Path) -> dict[str, int]:
    """numba's cache files under `folder`, with their modification times."""
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*.nb*")}


def test_first_run_says_it_compiles_and_links_warm_compiles_everything(tmp_path: Path) -> None:
    """With an empty numba cache, `links demo` says it compiles the solver (on stderr, stdout
    untouched); run again, it says nothing. `links warm` then fills the cache for every
    command: none has anything to say, and warming again writes no cache file (numba writes
    one only when it compiles)."""
    cache = tmp_path / "numba-cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        command = [sys.executable, "-m", "links_ray.cli", *args]
        return subprocess.run(command, capture_output=True, text=True, timeout=900, env=env)

    demo = ["demo", "--out", str(tmp_path / "demo"), "--mechanisms", "5", "--json"]
    first = run(*demo)
    assert first.returncode == 0, first.stderr
    assert first.stderr == (
        "links demo: compiling the solver's kernels (first run only, about 15 s)...\n"
    )
    assert json.loads(first.stdout)["mechanisms"] == 5
    again = run(*demo)
    assert again.returncode == 0 and again.stderr == ""

    # Each room of kernels is told by its own anchor: a cold cache names every group.
    cold = run_python(
        env, "from links_ray.cli.kernels import compile_notice\nprint(compile_notice('synthesize'))"
    )
    assert cold == (
        "links synthesize: compiling the search kernels and the path kernels and the refinement "
        "kernels and the refinement step's kernels (first run only, about 30 s)..."
    )
    warmed = run("warm", "--json")
    assert warmed.returncode == 0, warmed.stderr
    assert set(json.loads(warmed.stdout)) == {
        "rejection sampler",
        "generation",
        "curation",
        "search and synthesis",
    }
    notices = run_python(
        env,
        "from links_ray.cli.kernels import COMMAND_KERNELS, compile_notice\n"
        "print([n for n in map(compile_notice, COMMAND_KERNELS) if n])",
    )
    assert notices == "[]"
    before = cache_files(cache)
    assert len(before) > 50
    human = run("warm")
    assert human.returncode == 0, human.stderr
    assert human.stdout.splitlines()[-1] == "kernels compiled and cached"
    assert cache_files(cache) == before


def run_python(env: dict[str, str], code: str) -> str:
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()
