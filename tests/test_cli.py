"""`links`: the demo writes valid mechanisms, benchmarks print JSON, errors are one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

import links_ray
from links_ray.cli import bench
from links_ray.engine.mechanism import analyze_topology, dataset_rule_violations


def links(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "links_ray.cli", *args], capture_output=True, text=True, timeout=600
    )


def test_demo_writes_valid_mechanisms(tmp_path: Path) -> None:
    result = links("demo", "--out", str(tmp_path / "demo"), "--mechanisms", "12", "--seed", "3")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["mechanisms"] == 12 and summary["topologies"] == 3
    rows = [json.loads(line) for line in (tmp_path / "demo" / "mechanisms.jsonl").open()]
    assert [row["mechanism_id"] for row in rows] == list(range(12))
    assert json.loads((tmp_path / "demo" / "summary.json").read_text()) == summary
    for row in rows:
        positions = np.array(row["positions"])
        topology = analyze_topology(row["adjacency"], row["node_types"])
        assert dataset_rule_violations(topology, positions) == []
        path = links_ray.simulate(row["adjacency"], row["node_types"], positions)
        np.testing.assert_allclose(path[row["last_joint"]], row["last_joint_path"], atol=1e-6)


def test_bad_arguments_fail_with_one_line(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    result = links("demo", "--out", str(blocker / "sub"))
    assert result.returncode != 0
    assert len(result.stderr.strip().splitlines()) == 1 and "error" in result.stderr
    for bad in (["demo", "--mechanisms", "0"], ["generate", "--out", "x", "--mechanisms", "y"]):
        result = links(*bad)
        assert result.returncode == 2 and "positive" in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
    result = links("generate", "--out", "ftp://host/x", "--mechanisms", "5")
    assert result.returncode == 2 and "unsupported scheme" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_bench_simulate_reports_table1() -> None:
    result = bench.bench_simulate(repeats=1, reference_subset=4, topologies=4, per_topology=10)
    assert result["candidates"] == 40
    for key in ("compiled_1_thread", "compiled_all_cores", "valid_full_turn"):
        assert result[key]["mean_s"] > 0
    assert result["paper_s"]["vectorized_1_thread"] == 10.994
    assert "Table 1" in bench.format_simulate(result)


def test_bench_sample_cli_prints_json() -> None:
    result = links("bench", "sample", "--json", "--topologies", "1")
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    by_size = data["samplers"]["rejection"]["by_joint_count"]
    assert sorted(map(int, by_size)) == list(range(8, 21))
    assert data["samplers"]["sequential"]["valid_per_core_second"] > 0
