"""`links`: the demo writes valid mechanisms, benchmarks print JSON, errors are one line."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import links_ray
from links_ray.bench import engine as bench
from links_ray.engine.kinematics.mechanism import (
    LockingError,
    analyze_topology,
    dataset_rule_violations,
)
from links_ray.engine.kinematics.reference import simulate_reference
from links_ray.engine.kinematics.sampling import measure_candidates_per_valid
from tests.support.cli import links


@pytest.mark.parametrize("module", ["links_ray.cli", "links_ray"])
def test_version(module: str) -> None:
    """`links --version` and `python -m links_ray --version` name the installed package."""
    result = subprocess.run(
        [sys.executable, "-m", module, "--version"], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"links-ray {links_ray.__version__}"


def test_demo_writes_valid_mechanisms(tmp_path: Path) -> None:
    """12 mechanisms at five variants per topology: topologies 0, 1 and 2 (two variants of the
    last), every row valid by the dataset rules and its stored path re-simulated."""
    result = links(
        "demo", "--out", str(tmp_path / "demo"), "--mechanisms", "12", "--seed", "3", "--json"
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["mechanisms"] == 12 and summary["topologies"] == 3
    rows = [json.loads(line) for line in (tmp_path / "demo" / "mechanisms.jsonl").open()]
    assert [row["mechanism_id"] for row in rows] == list(range(12))
    assert [row["topology_id"] for row in rows] == [0] * 5 + [1] * 5 + [2] * 2
    assert [row["variant"] for row in rows] == [0, 1, 2, 3, 4] * 2 + [0, 1]
    sizes = Counter(str(len(row["node_types"])) for row in rows)
    assert summary["joint_counts"] == dict(sizes)
    assert json.loads((tmp_path / "demo" / "summary.json").read_text()) == summary
    for row in rows:
        first = rows[5 * row["topology_id"]]
        assert (row["adjacency"], row["node_types"]) == (first["adjacency"], first["node_types"])
        positions = np.array(row["positions"])
        topology = analyze_topology(row["adjacency"], row["node_types"])
        assert dataset_rule_violations(topology, positions) == []
        assert row["last_joint"] == topology.last_joint
        path = links_ray.simulate(row["adjacency"], row["node_types"], positions)
        np.testing.assert_allclose(path[row["last_joint"]], row["last_joint_path"], atol=1e-6)
    # A whole number of candidates for the 15 valid sets of three topologies, at least 15.
    candidates = 15 * summary["candidates_per_valid"]
    assert candidates == pytest.approx(round(candidates)) and round(candidates) >= 15


def local_links(*args: str) -> subprocess.CompletedProcess[str]:
    """`links` as a user runs it on a laptop: a Ray of its own, Ray's settings left alone."""
    env = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "RAY_AUTH_MODE")}
    return subprocess.run(
        [sys.executable, "-m", "links_ray.cli", *args],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )


def table_rows(text: str, first: str) -> list[list[str]]:
    """The rows under the table header that starts with `first`, up to a line that is not
    one."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.split()[:1] == [first])
    width = len(lines[start].split())
    rows = []
    for line in lines[start + 1 :]:
        if len(line.split()) != width:
            break
        rows.append(line.split())
    return rows


#: What a local run used to print on stderr that its user can do nothing about.
RAY_NOISE = ("Token authentication", "Progress bars disabled", "deprecated", "Traceback")


@pytest.mark.ray  # a local Ray of the command's own
def test_generate_and_curate_print_short_summaries(tmp_path: Path) -> None:
    """On a local Ray: a few lines and one row per joint count (topology i has 8 + i % 13
    joints: 30 mechanisms are six topologies of 8 to 13), counts as the tables hold them, the
    whole summary with --json, and none of Ray's notices."""
    out = tmp_path / "data"
    plan = ["--out", str(out), "--mechanisms", "30", "--shard-topologies", "2"]
    made = local_links("generate", *plan)
    assert made.returncode == 0, made.stderr
    assert [line for line in made.stderr.splitlines() if any(n in line for n in RAY_NOISE)] == []
    assert len(made.stdout.splitlines()) <= 20
    assert made.stdout.startswith(f"{out}: 30 mechanisms (complete); mechanisms 30, ")
    rows = table_rows(made.stdout, "joints")
    assert [(int(row[0]), int(row[2])) for row in rows] == [(n, 5) for n in range(8, 14)]
    mechanisms = links_ray.load(str(out), "mechanisms", columns=["n_joints"])
    assert sorted(Counter(mechanisms["n_joints"]).items()) == [(n, 5) for n in range(8, 14)]

    again = links("generate", *plan, "--json")  # finished: no Ray, the saved summary
    assert again.returncode == 0, again.stderr
    assert "nothing to do" in again.stderr
    saved = json.loads((out / "_links" / "summary.json").read_text())
    assert json.loads(again.stdout) == {**saved, "nothing_to_do": True}

    curated = local_links("curate", str(out))
    assert curated.returncode == 0, curated.stderr
    noise = [line for line in curated.stderr.splitlines() if any(n in line for n in RAY_NOISE)]
    assert noise == []
    paths = len(links_ray.load(str(out), "paths", columns=["path_id"]))
    kept = len(links_ray.load(str(out), "curated", columns=["path_id"]))
    assert curated.stdout.startswith(
        f"{out}: 30 mechanisms made {paths:,} paths, {kept:,} curated "
        f"({100 * kept / paths:.1f}%); wrote paths, curated\n"
    )
    flags = links_ray.load(str(out), "paths", columns=["is_arc", "is_circle"])
    named = {line.split()[0]: line.split() for line in curated.stdout.splitlines() if line}
    circles = int(flags["is_circle"].sum())
    assert named["circles"][1:] == [f"{circles:,}", f"{100 * circles / paths:.1f}%"]
    assert named["arcs"][1] == f"{int(flags['is_arc'].sum()):,}"
    assert len(curated.stdout.splitlines()) <= 12


def test_bad_arguments_fail_with_one_line(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    result = links("demo", "--out", str(blocker / "sub"))
    assert result.returncode == 2
    assert result.stderr == f"links demo: error: [Errno 20] Not a directory: '{blocker / 'sub'}'\n"
    for bad, what in (
        (["demo", "--mechanisms", "0"], "got 0"),
        (["generate", "--out", "x", "--mechanisms", "y"], "got y"),
    ):
        result = links(*bad)
        assert result.returncode == 2
        assert result.stderr == (
            f"links {bad[0]}: error: argument --mechanisms: must be a positive integer, "
            f"{what} (see --help)\n"
        )
    for port in ("70000", "0"):
        result = links("serve", str(tmp_path), "--port", port)
        assert result.returncode == 2
        assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
        assert result.stderr.startswith("links serve: error: argument --port: must be a ")
    result = links("curate", str(tmp_path), "--store", "all")
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert result.stderr.startswith("links curate: error: argument --store: invalid choice: 'all'")
    result = links("generate", "--out", "ftp://host/x", "--mechanisms", "5")
    assert result.returncode == 2
    assert result.stderr == (
        "links generate: error: unsupported scheme 'ftp' in ftp://host/x: use a folder or s3://\n"
    )


def test_index_saves_every_part_for_a_later_open_to_load(dataset: str, tmp_path: Path) -> None:
    """`links index ROOT --shards 2` builds and saves both parts, which a later open (a Serve
    replica's) loads without building; run again it builds nothing, `--rebuild` builds both
    again, without `--shards` it saves the one index, and a split with an empty part is
    refused in one line."""
    from links_ray.search.cache import INDEX_FOLDER
    from links_ray.search.index import RetrievalIndex

    root = tmp_path / "data"
    shutil.copytree(dataset, root)
    shutil.rmtree(root / INDEX_FOLDER, ignore_errors=True)  # the fixture's own saved index
    curated = len(links_ray.load(str(root), "curated", columns=["path_id"]))
    assert curated > 0

    made = links("index", str(root), "--shards", "2", "--json")
    assert made.returncode == 0, made.stderr
    summary = json.loads(made.stdout)
    assert (summary["parts"], summary["built"], summary["paths"]) == (2, 2, curated)
    assert summary["folder"] == f"{root}/{INDEX_FOLDER}"
    assert [entry["part"] for entry in summary["by_part"]] == [0, 1]
    for entry in summary["by_part"]:
        loaded = RetrievalIndex.open(str(root), part=entry["part"], parts=2)
        assert entry["built"] and loaded.build_s == 0 and len(loaded) == entry["paths"] > 0

    again = links("index", str(root), "--shards", "2")
    assert again.returncode == 0, again.stderr
    (line,) = again.stdout.splitlines()
    assert line.startswith(
        f"{root}: {curated:,} paths indexed in 2 parts (0 built, 2 already saved) "
        f"under {root}/{INDEX_FOLDER}/ in "
    )

    rebuilt = links("index", str(root), "--shards", "2", "--rebuild", "--json")
    assert rebuilt.returncode == 0, rebuilt.stderr
    assert json.loads(rebuilt.stdout)["built"] == 2

    whole = links("index", str(root), "--json")
    assert whole.returncode == 0, whole.stderr
    assert {k: json.loads(whole.stdout)[k] for k in ("parts", "built", "paths")} == {
        "parts": 1,
        "built": 1,
        "paths": curated,
    }
    assert RetrievalIndex.open(str(root)).build_s == 0

    refused = links("index", str(root), "--shards", "1000")
    assert refused.returncode == 2
    assert refused.stderr.count("\n") == 1 and "Traceback" not in refused.stderr
    assert refused.stderr.startswith(f"links index: error: {root} has ")
    assert refused.stderr.rstrip().endswith("would have none; use a smaller --shards")


def count_valid_by_reference(workload: bench.Workload, steps: int) -> int:
    """Candidates of a workload that the plain-Python solver turns a full crank without a lock."""
    valid = 0
    for adjacency, node_types, positions in workload:
        for candidate in positions:
            try:
                simulate_reference(adjacency, node_types, candidate, steps)
            except LockingError:
                continue
            valid += 1
    return valid


def test_bench_simulate_reports_table1() -> None:
    """The counts come from the plan (4 topologies x 10 candidates, one per topology for the
    plain solver) and the valid count from the reference solver; timings are consistent."""
    result = bench.bench_simulate(repeats=2, reference_subset=4, topologies=4, per_topology=10)
    assert result["candidates"] == 40 and result["topologies"] == 4 and result["steps"] == 200
    workload = bench.table1_workload(topologies=4, per_topology=10, seed=0)
    assert result["valid_candidates"] == count_valid_by_reference(workload, 200)
    reference = result["non_vectorized_1_thread"]
    assert reference["subset"] == 4
    assert reference["scaled_s"] == pytest.approx(reference["subset_s"] * 40 / 4)
    for key in ("compiled_1_thread", "compiled_all_cores", "valid_full_turn"):
        timing = result[key]
        assert 0 < timing["best_s"] <= timing["mean_s"] and timing["std_s"] >= 0
    assert result["compiled_all_cores"]["threads"] == os.cpu_count()
    full = result["valid_full_turn"]
    assert full["mechanisms"] == 40
    assert full["per_second_per_core"] == pytest.approx(40 / full["best_s"])
    assert result["paper_s"]["vectorized_1_thread"] == 10.994
    text = bench.format_simulate(result)
    assert "Table 1: 40 random candidates (4 topologies" in text
    assert f"{result['valid_candidates']} valid)" in text


def test_bench_simulate_one_cli_prints_json() -> None:
    """Every entry point's row counts the mechanisms it turned (five per topology, the last
    topology cut short for `simulate`'s rows); the rates follow from the timings; the
    mechanisms are valid ones (each turns in the plain-Python solver)."""
    result = links("bench", "simulate-one", "--json", "--mechanisms", "7")
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["benchmark"] == "simulate-one" and data["topologies"] == 2
    rows = data["entry_points"]
    assert set(rows) == {
        "simulate",
        "simulate_new_topology",
        "prebuilt_one",
        "prebuilt_topology",
        "simulate_batch",
    }
    for name, row in rows.items():
        assert row["mechanisms"] == (10 if name in ("prebuilt_topology", "simulate_batch") else 7)
        assert row["turns_per_second"] == pytest.approx(row["mechanisms"] / row["best_s"])
        assert row["turns_per_second_low"] <= row["turns_per_second_median"]
        assert row["turns_per_second_median"] <= row["turns_per_second"]
    workload = bench.valid_mechanisms(2, 5, seed=0)
    assert [len(positions) for _, _, positions in workload] == [5, 5]
    for adjacency, node_types, positions in workload:
        for candidate in positions:
            simulate_reference(adjacency, node_types, candidate, 200)  # raises if it locks
    text = bench.format_simulate_one(data)
    assert "links_ray.simulate, one mechanism a call" in text


def test_bench_sample_cli_prints_json() -> None:
    """Both samplers see the same topologies (the seed's), so each sampler's candidates per
    valid set are those of measuring it directly; the throughput follows from the entries."""
    result = links("bench", "sample", "--json", "--topologies", "1")
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["count"] == 5
    for kind in ("rejection", "sequential"):
        by_size = data["samplers"][kind]["by_joint_count"]
        assert sorted(map(int, by_size)) == list(range(8, 21))
        direct = measure_candidates_per_valid(range(8, 21), 1, 5, np.random.default_rng(0), kind)
        for n, entry in by_size.items():
            assert entry["candidates_per_valid"] == direct[int(n)]["candidates_per_valid"]
            assert entry["abandoned"] == direct[int(n)]["abandoned"]
            assert entry["candidates_per_valid"] >= 1
        # 5 valid sets of one topology per joint count, over the seconds each took.
        seconds = sum(5 / entry["valid_per_second"] for entry in by_size.values())
        throughput = data["samplers"][kind]["valid_per_core_second"]
        assert throughput == pytest.approx(5 * 13 / seconds, rel=1e-12)


def _parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """A parser and every subcommand's, at any depth."""
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


def test_every_option_says_its_default() -> None:
    """In `--help`, every option with a default names it (`links serve --help`: port 8000)."""
    from links_ray.cli.main import build_parser

    silent = []
    for parser in _parsers(build_parser()):
        for action in parser._actions:
            has_default = not any(
                action.default is nothing for nothing in (None, False, argparse.SUPPRESS)
            )
            if action.option_strings and has_default and "default" not in (action.help or ""):
                silent.append(f"{parser.prog} {action.option_strings[0]}")
    assert silent == []
    assert "(default 8000)" in " ".join(links("serve", "--help").stdout.split())
