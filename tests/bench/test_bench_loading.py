"""The benchmarks are a room of their own: `links --help` and every other command line load
none of them, and `links bench` still lists them all."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.support.package_imports import REPO

PROBE = """
import contextlib, io, json, sys
from links_ray.cli.main import main
with contextlib.redirect_stdout(io.StringIO()) as out:
    try:
        main(sys.argv[1:])
    except SystemExit:
        pass
loaded = sorted(m for m in sys.modules if m.split(".")[:2] == ["links_ray", "bench"])
print(json.dumps([loaded, out.getvalue()]))
"""


def loaded_by(*argv: str) -> tuple[list[str], str]:
    """The benchmark modules a fresh process loads for `links ARGV`, and what it printed."""
    done = subprocess.run(
        [sys.executable, "-c", PROBE, *argv], cwd=REPO, capture_output=True, text=True, check=True
    )
    loaded, printed = json.loads(done.stdout.splitlines()[-1])
    return loaded, printed


@pytest.mark.parametrize("argv", [("--help",), ("generate", "--help"), ("stats", "--help")])
def test_other_command_lines_load_no_benchmark(argv: tuple[str, ...]) -> None:
    loaded, printed = loaded_by(*argv)
    assert loaded == []
    assert printed.startswith("usage: links")


def test_links_help_names_bench_and_links_bench_lists_every_benchmark() -> None:
    from links_ray.bench.command import BENCHMARKS

    _, top = loaded_by("--help")
    assert "bench" in top and "benchmarks" in top
    loaded, listed = loaded_by("bench", "--help")
    assert "links_ray.bench.command" in loaded
    for benchmark in BENCHMARKS:
        assert benchmark.name in listed
