"""`links stats` without reading what it need not: counts from the commit markers equal to
the rows a plain read finds, shares counted batch by batch equal to whole-table counts, and
the transmission quantiles those of numpy on the whole column; candidates per valid mechanism
measured only when asked, else the rejection run's own, else null and why; the command's
table and JSON telling the same counts. Made without Ray."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pyarrow.dataset as pads
import pytest

from links_ray.cli import report
from links_ray.cluster.generation import summarize
from links_ray.data.commit import committed_shards
from links_ray.data.generation import GenerationPlan
from links_ray.data.schemas import TABLE_NAMES
from links_ray.data.stats import TRANSMISSION_QUANTILES, dataset_stats
from links_ray.data.store import META, Store
from links_ray.engine.kinematics.sampling import measure_candidates_per_valid
from tests.support.cli import links
from tests.support.local_dataset import generate_and_curate


def generated(root: str, plan: GenerationPlan) -> str:
    """`plan` generated and curated into `root`, with the run summary `links generate` saves
    (`cluster.generation.summarize` of the same markers)."""
    generate_and_curate(root, plan)
    store = Store.open(root)
    markers = committed_shards(store, "shards")
    summary = summarize(plan, markers, store.uri, 1.0, 1, plan.mechanisms)
    store.write_json(f"{META}/summary.json", summary)
    return root


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> str:
    folder = tmp_path_factory.mktemp("stats")
    return generated(str(folder / "root"), GenerationPlan(seed=4, mechanisms=263))


def test_stats_are_those_of_the_rows(root: str) -> None:
    stats = dataset_stats(root)
    for table in TABLE_NAMES:
        rows = pads.dataset(f"{root}/{table}", partitioning="hive").to_table()
        sizes = Counter(rows.column("n_joints").to_pylist())
        assert stats["counts"][table] == {
            "rows": len(rows),
            "by_joint_count": {str(n): sizes[n] for n in sorted(sizes)},
        }, table
        if table in ("paths", "curated"):
            arc, circle = (
                rows.column(c).to_numpy(zero_copy_only=False) for c in ("is_arc", "is_circle")
            )
            shares = stats["shares"][table]
            assert shares["paths"] == len(rows)
            assert shares["circle"] == circle.sum() / len(rows)
            assert shares["arc_not_circle"] == (arc & ~circle).sum() / len(rows)
    angles = pads.dataset(f"{root}/mechanisms", partitioning="hive").to_table()
    degrees = np.sort(angles.column("min_transmission_deg").to_numpy())
    transmission = stats["min_transmission_deg"]
    expected = np.quantile(degrees, TRANSMISSION_QUANTILES)
    assert [transmission["quantiles"][str(q)] for q in TRANSMISSION_QUANTILES] == expected.tolist()
    assert transmission["share_below"]["10"] == np.mean(degrees < 10)
    assert sum(transmission["histogram"]["counts"]) == len(degrees) == 263


def test_markers_that_claim_more_rows_than_the_files_hold_are_refused(
    root: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """A marker's word is not trusted with memory: one claiming a trillion mechanisms is
    refused in one line, allocating nothing of the sort."""
    lying = tmp_path_factory.mktemp("lying") / "root"
    shutil.copytree(root, lying)
    marker_path = sorted((lying / "_links" / "shards").glob("shard-*.json"))[0]
    marker = json.loads(marker_path.read_text())
    marker["rows"]["mechanisms"] = 10**12
    marker_path.write_text(json.dumps(marker))
    with pytest.raises(ValueError, match=r"holds 263 rows, its commit markers say 1,000,000,000,2"):
        dataset_stats(str(lying))


# -- candidates per valid mechanism -----------------------------------------------------------


def measured_directly(topologies: int) -> dict[str, float]:
    """The rejection sampler's candidates per valid on `topologies` topologies per joint count,
    five variants each, seed 0, measured without `links stats`."""
    by_size = measure_candidates_per_valid(
        range(8, 21), topologies, 5, np.random.default_rng(0), "rejection", max_candidates=200_000
    )
    return {str(n): entry["candidates_per_valid"] for n, entry in by_size.items()}


def test_candidates_per_valid_of_a_sequential_root_are_measured_only_when_asked(
    root: str, tmp_path: Path
) -> None:
    """The default sampler's root records no candidates of the paper's sampler: null and the
    reason, naming the option, unless asked; asked, the sampler's figure on the sample asked."""
    unasked = dataset_stats(root)
    assert unasked["candidates_per_valid"] is None
    assert unasked["candidates_per_valid_sample"] is None
    source = unasked["candidates_per_valid_source"]
    assert source.startswith("not measured (the root was made by the sequential sampler)")
    assert "--measure-candidates N" in source

    asked = dataset_stats(root, sample_topologies=2)
    assert asked["candidates_per_valid"] == measured_directly(2)
    assert asked["candidates_per_valid_sample"] == {
        "sampler": "rejection",
        "topologies_per_joint_count": 2,
        "variants": 5,
        "max_candidates": 200_000,
        "seed": 0,
    }
    assert asked["candidates_per_valid_source"].startswith("measured here")
    assert {k: v for k, v in asked.items() if not k.startswith("candidates_per_valid")} == {
        k: v for k, v in unasked.items() if not k.startswith("candidates_per_valid")
    }
    with pytest.raises(ValueError, match="sample_topologies must be a positive integer, got 0"):
        dataset_stats(root, sample_topologies=0)

    # No figure of what was not measured; the others all the same.
    from links_ray.cli.figures import write_figures

    written = write_figures(root, tmp_path / "plots", unasked)
    assert sorted(Path(path).name for path in written) == [
        "curation.png",
        "joint_counts.png",
        "mechanisms.png",
    ]


def test_a_rejection_root_reports_its_own_run_and_measures_when_asked(
    tmp_path: Path,
) -> None:
    """The paper's sampler counted its candidates as it made the root: those, by joint count,
    without measuring; a root without a run summary (an imported one) says so."""
    rejection = generated(
        str(tmp_path / "rejection"), GenerationPlan(seed=2, mechanisms=65, sampler="rejection")
    )
    run = Store.open(rejection).read_json(f"{META}/summary.json")
    stats = dataset_stats(rejection)
    assert stats["candidates_per_valid"] == {
        size: entry["candidates"] / entry["valid"] for size, entry in run["by_joint_count"].items()
    }
    assert len(stats["candidates_per_valid"]) == 13
    assert stats["candidates_per_valid_source"] == "the generation run (rejection sampler)"
    assert stats["candidates_per_valid_sample"] is None
    asked = dataset_stats(rejection, sample_topologies=1)
    assert asked["candidates_per_valid"] == measured_directly(1)
    assert asked["candidates_per_valid_sample"]["topologies_per_joint_count"] == 1

    (tmp_path / "rejection" / "_links" / "summary.json").unlink()
    unrecorded = dataset_stats(rejection)
    assert unrecorded["candidates_per_valid"] is None
    assert unrecorded["candidates_per_valid_source"].startswith(
        "not measured (no generation run recorded)"
    )


# -- the command ------------------------------------------------------------------------------


def table_rows(text: str) -> tuple[list[str], dict[str, list[str]]]:
    """The joint-count table of `links stats`' output: its header, and its rows by first
    cell (8 to 20, then "all")."""
    lines = text.splitlines()
    start = next(k for k, line in enumerate(lines) if line.startswith("joints"))
    rows = {}
    for line in lines[start + 1 :]:
        cells = line.split()
        rows[cells[0]] = cells[1:]
        if cells[0] == "all":
            break
    return lines[start].split(), rows


def test_links_stats_prints_the_table_piped_and_json_when_asked(root: str) -> None:
    """Piped (as here), a table; its counts by joint count are those `--json` prints."""
    piped = links("stats", root)
    assert piped.returncode == 0, piped.stderr
    header, rows = table_rows(piped.stdout)
    as_json = links("stats", root, "--json")
    assert as_json.returncode == 0, as_json.stderr
    stats = json.loads(as_json.stdout)
    tables = [name for name in TABLE_NAMES if stats["counts"][name]]
    assert header == ["joints", *tables]  # no column of candidates: not measured
    sizes = [str(n) for n in range(8, 21)]
    assert list(rows) == [*sizes, "all"]
    for column, table in enumerate(tables):
        counts = stats["counts"][table]
        assert [int(rows[n][column].replace(",", "")) for n in sizes] == [
            counts["by_joint_count"].get(n, 0) for n in sizes
        ], table
        assert int(rows["all"][column].replace(",", "")) == counts["rows"]
    assert sum(stats["counts"]["mechanisms"]["by_joint_count"].values()) == 263
    said = next(line for line in piped.stdout.splitlines() if line.startswith("candidates/valid"))
    assert said == f"candidates/valid: {stats['candidates_per_valid_source']}"
    assert stats["candidates_per_valid"] is None and "--measure-candidates N" in said


def test_links_stats_measures_candidates_when_asked(root: str) -> None:
    """`--measure-candidates 1`: a column of the sampler's figure on one topology a joint
    count, the figure `--json` prints with its sample."""
    asked = links("stats", root, "--measure-candidates", "1")
    assert asked.returncode == 0, asked.stderr
    header, rows = table_rows(asked.stdout)
    assert header[-1] == "candidates/valid"
    expected = measured_directly(1)
    assert [rows[n][-1] for n in expected] == [report.number(v) for v in expected.values()]
    stats = json.loads(links("stats", root, "--measure-candidates", "1", "--json").stdout)
    assert stats["candidates_per_valid"] == expected
    assert stats["candidates_per_valid_sample"]["topologies_per_joint_count"] == 1


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--measure-candidates", "0"], "--measure-candidates: must be a positive integer, got 0"),
        (["--measure-candidates", "-2"], "must be a positive integer, got -2"),
        (["--measure-candidates", "some"], "must be a positive integer, got some"),
        (["--measure-candidates"], "--measure-candidates: expected one argument"),
        (["--table"], "unrecognized arguments: --table"),
        (["--sample-topologies", "1"], "unrecognized arguments: --sample-topologies 1"),
    ],
)
def test_links_stats_refuses_bad_options_in_one_line(root: str, args: list[str], says: str) -> None:
    done = links("stats", root, *args)
    assert done.returncode == 2
    assert done.stdout == ""
    assert len(done.stderr.splitlines()) == 1 and says in done.stderr, done.stderr
