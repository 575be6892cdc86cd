"""Curation on Ray Data, the loading helper and `links stats`, on real generated data.

Every path row is checked against the definitions (docs/reference/contract.md, Paths) from the
mechanism and simulation rows it came from; curation's kept share is checked against binomial
bounds.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

import links_ray
from links_ray.cluster.curation import curate
from links_ray.cluster.generation import generate
from links_ray.data import curation as data_curation
from links_ray.data import schemas
from links_ray.data.commit import committed_files, committed_shards, marker_file
from links_ray.data.curation import KEEP_SHARE, keep_draw, path_table
from links_ray.data.schemas import CURATION_TABLES
from links_ray.data.store import META, Store, StoreError
from links_ray.engine.kinematics.paths import circle_variance, normalize_path
from links_ray.engine.kinematics.sampling import measure_candidates_per_valid
from tests.cluster.test_generation import assert_only_committed_files, read_table
from tests.support.cli import links

MECHANISMS = 300
#: The plan of `curated_run`: topology i has 8 + i % 13 joints and five variants, and each joint
#: count's topologies go in shards of TOPOLOGIES_PER_SHARD.
TOPOLOGIES, TOPOLOGIES_PER_SHARD = MECHANISMS // 5, 4
TOPOLOGIES_BY_SIZE = Counter(8 + i % 13 for i in range(TOPOLOGIES))


def shares_of(paths: pa.Table) -> dict[str, float]:
    """The shares of arcs and circles among path rows, counted here from the rows."""
    arc = paths.column("is_arc").to_numpy()
    circle = paths.column("is_circle").to_numpy()
    return {
        "circle": circle.mean(),
        "arc": arc.mean(),
        "arc_or_circle": (arc | circle).mean(),
        "both": (arc & circle).mean(),
    }


@pytest.fixture(scope="module")
def curated_run(ray_cluster: str, tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = str(tmp_path_factory.mktemp("curation") / "data")
    generate(out, MECHANISMS, seed=7, progress=False, topologies_per_shard=TOPOLOGIES_PER_SHARD)
    summary = curate(out, seed=11, progress=False)
    store = Store.open(out)
    return {
        "out": out,
        "summary": summary,
        "paths": read_table(store, "paths").sort_by("path_id"),
        "curated": read_table(store, "curated").sort_by("path_id"),
        "mechanisms": read_table(store, "mechanisms"),
        "simulations": read_table(store, "simulations"),
    }


def binomial_interval(n: int, p: float, tail: float = 1e-6) -> tuple[int, int]:
    """The central range of Binomial(n, p) holding all but `tail` of each side."""
    log_pmf = [
        math.lgamma(n + 1)
        - math.lgamma(k + 1)
        - math.lgamma(n - k + 1)
        + k * math.log(p)
        + (n - k) * math.log1p(-p)
        for k in range(n + 1)
    ]
    cdf = np.cumsum(np.exp(log_pmf))
    return int(np.searchsorted(cdf, tail)), int(np.searchsorted(cdf, 1 - tail))


def test_one_normalized_path_per_moving_joint(curated_run: dict) -> None:
    paths = curated_run["paths"].to_pylist()
    by_mechanism: dict[int, list[dict]] = {}
    for row in paths:
        by_mechanism.setdefault(row["mechanism_id"], []).append(row)
        assert row["path_id"] == 32 * row["mechanism_id"] + row["joint"]
    assert len({row["path_id"] for row in paths}) == len(paths)
    simulations = {row["mechanism_id"]: row for row in curated_run["simulations"].to_pylist()}
    mechanisms = curated_run["mechanisms"].to_pylist()
    assert len(mechanisms) == MECHANISMS
    # Every path is a mechanism's (each of which is checked below).
    assert by_mechanism.keys() == {mechanism["mechanism_id"] for mechanism in mechanisms}
    for mechanism in mechanisms:
        n = mechanism["n_joints"]
        types = np.array(mechanism["node_types"])
        adjacency = np.array(mechanism["adjacency"]).reshape(n, n)
        rows = by_mechanism[mechanism["mechanism_id"]]
        assert sorted(row["joint"] for row in rows) == np.flatnonzero(types != 0).tolist()
        traced = np.array(simulations[mechanism["mechanism_id"]]["trajectories"]).reshape(n, -1, 2)
        for row in rows:
            points = np.array(row["points"], dtype=np.float32).reshape(-1, 2)
            np.testing.assert_allclose(points, normalize_path(traced[row["joint"]]), atol=2e-6)
            assert row["is_arc"] == bool(np.any(adjacency[row["joint"]] & (types == 0)))
            variance = circle_variance(points)
            assert row["is_circle"] == (variance < 5e-4)
            assert row["circle_variance"] == pytest.approx(variance, rel=1e-5, abs=1e-9)
            # Normalized: the longest chord has length 1 and the box is centred at 0.5.
            gaps = np.linalg.norm(points[:, None] - points[None], axis=-1)
            assert gaps.max() == pytest.approx(1.0, abs=1e-5)
            box = (points.min(axis=0) + points.max(axis=0)) / 2
            np.testing.assert_allclose(box, 0.5, atol=1e-6)


def test_curated_keeps_the_rest_and_a_seeded_half_percent(curated_run: dict) -> None:
    paths, curated = curated_run["paths"], curated_run["curated"]
    common = paths.column("is_arc").to_numpy() | paths.column("is_circle").to_numpy()
    ids = paths.column("path_id").to_numpy()
    kept = set(curated.column("path_id").to_pylist())
    assert set(ids[~common]) <= kept, "every path that is neither arc nor circle is kept"
    lucky = ids[common][keep_draw(ids[common], 11) < KEEP_SHARE]
    assert kept == set(ids[~common]) | set(lucky)
    low, high = binomial_interval(int(common.sum()), KEEP_SHARE)
    assert low <= len(lucky) <= high
    assert curated.equals(paths.filter(np.isin(ids, list(kept))))


def test_a_finished_pass_leaves_only_committed_files(curated_run: dict) -> None:
    assert_only_committed_files(curated_run["out"], CURATION_TABLES)
    assert_only_committed_files(curated_run["out"])


def test_summary_counts_are_the_rows(curated_run: dict) -> None:
    """Every count and share of the curation summary, against the rows and the plan."""
    paths, curated = curated_run["paths"], curated_run["curated"]
    summary = curated_run["summary"]
    shards = sum(-(-count // TOPOLOGIES_PER_SHARD) for count in TOPOLOGIES_BY_SIZE.values())
    assert summary["shards"] == summary["shards_this_run"] == shards == 21
    assert summary["mechanisms"] == MECHANISMS
    assert summary["paths"] == len(paths) and summary["curated"] == len(curated)
    arc = paths.column("is_arc").to_numpy()
    circle = paths.column("is_circle").to_numpy()
    assert summary["arcs"] == arc.sum() and summary["circles"] == circle.sum()
    assert summary["both"] == (arc & circle).sum()
    assert summary["shares"].keys() == shares_of(paths).keys()
    for key, share in shares_of(paths).items():
        assert summary["shares"][key] == pytest.approx(share, rel=1e-12), key
    # One path per moving joint: the mechanisms' moving joints, counted from their rows.
    moving = sum(
        sum(t != 0 for t in types)
        for types in curated_run["mechanisms"].column("node_types").to_pylist()
    )
    assert len(paths) == moving


def test_keep_draw_is_uniform_and_seeded() -> None:
    ids = np.arange(2_000_000, dtype=np.int64) * 32 + 7
    draw = keep_draw(ids, 3)
    share = (draw < KEEP_SHARE).mean()
    sigma = math.sqrt(KEEP_SHARE * (1 - KEEP_SHARE) / len(ids))
    assert abs(share - KEEP_SHARE) < 5 * sigma
    assert abs(draw.mean() - 0.5) < 0.002 and draw.min() >= 0 and draw.max() < 1
    other = keep_draw(ids, 4) < KEEP_SHARE
    assert (other & (draw < KEEP_SHARE)).mean() < 3 * KEEP_SHARE**2, "seeds draw independently"
    np.testing.assert_array_equal(keep_draw(ids, 3), draw)


def test_rerun_and_fresh_curation_give_identical_rows(curated_run: dict) -> None:
    out = curated_run["out"]
    again = curate(out, seed=11, progress=False)
    assert again["shards_this_run"] == 0 and again["paths"] == curated_run["summary"]["paths"]
    copy = Path(out).parent / "copy"
    shutil.copytree(out, copy)
    for table in CURATION_TABLES:
        shutil.rmtree(copy / table)
    shutil.rmtree(copy / META / "curation")
    (copy / META / "curation.json").unlink()
    fresh = curate(str(copy), seed=11, progress=False)
    assert fresh["shards_this_run"] == fresh["shards"]
    store = Store.open(str(copy))
    for table in CURATION_TABLES:
        assert read_table(store, table).sort_by("path_id").equals(curated_run[table])
    with pytest.raises(StoreError, match="seed=11"):
        curate(out, seed=12, progress=False)


def _curator_pids() -> list[int]:
    """The worker processes of this session's Ray (children of its raylet) that hold a
    `ShardCurator` actor; none of any other Ray on the machine."""
    import ray
    from ray._private import ray_constants

    node = ray._private.worker._global_node
    raylet = node.all_processes[ray_constants.PROCESS_TYPE_RAYLET][0].process.pid
    listing = subprocess.run(
        ["ps", "-eo", "pid=,ppid=,args="], capture_output=True, text=True, check=True
    ).stdout
    rows = [line.split(None, 2) for line in listing.splitlines()]
    return [
        int(row[0])
        for row in rows
        if len(row) == 3 and int(row[1]) == raylet and "ShardCurator" in row[2]
    ]


def test_a_curator_lost_mid_pass_changes_no_row(curated_run: dict) -> None:
    """A curator's worker killed once the pass has committed a shard: the run makes another
    pass over the shards left, and its rows are the undisturbed run's."""
    copy = Path(curated_run["out"]).parent / "lost-curator"
    shutil.copytree(curated_run["out"], copy)
    for table in CURATION_TABLES:
        shutil.rmtree(copy / table)
    shutil.rmtree(copy / META / "curation")
    (copy / META / "curation.json").unlink()
    store = Store.open(str(copy))
    shards = len(committed_shards(store))
    killed: dict[str, int] = {}

    def kill_a_curator() -> None:
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline:
            done = len(committed_shards(store, "curation"))
            pids = _curator_pids() if done else []
            if pids:
                os.kill(pids[0], signal.SIGKILL)
                killed.update(pid=pids[0], done=done)
                return
            time.sleep(0.1)

    killer = threading.Thread(target=kill_a_curator, daemon=True)
    killer.start()
    summary = curate(str(copy), seed=11, progress=False)
    killer.join(timeout=5)
    assert killed and 0 < killed["done"] < shards, killed  # killed while shards were left
    assert summary["shards_this_run"] == summary["shards"] == shards
    for table in CURATION_TABLES:
        assert read_table(store, table).sort_by("path_id").equals(curated_run[table])
    assert_only_committed_files(str(copy), CURATION_TABLES)


def test_curation_on_s3_matches_local(ray_cluster: str, s3_env: str, curated_run: dict) -> None:
    uri = f"{s3_env}/links"
    generate(uri, MECHANISMS, seed=7, progress=False, topologies_per_shard=30)
    summary = curate(uri, seed=11, progress=False)
    assert summary["curated"] == len(curated_run["curated"])
    store = Store.open(uri)
    for table in CURATION_TABLES:
        assert read_table(store, table).sort_by("path_id").equals(curated_run[table])
    assert_only_committed_files(uri, CURATION_TABLES)
    frame = links_ray.load(uri, "curated", n_joints=[9, 10])
    sizes = curated_run["curated"].column("n_joints").to_numpy()
    assert set(frame["n_joints"]) == {9, 10} and len(frame) == np.isin(sizes, [9, 10]).sum()


def read_curation(uri: str) -> dict[str, pa.Table | None]:
    """Each curation table's rows by path_id, None for a table the pass did not write."""
    store = Store.open(uri)
    return {
        table: read_table(store, table).sort_by("path_id") if store.list_files(table) else None
        for table in CURATION_TABLES
    }


@pytest.fixture(scope="module")
def mechanisms_only_run(ray_cluster: str, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """`curated_run`'s plan generated with `mechanisms` alone (same seed), then curated."""
    out = str(tmp_path_factory.mktemp("mechanisms-only") / "data")
    generate(
        out,
        MECHANISMS,
        seed=7,
        progress=False,
        topologies_per_shard=TOPOLOGIES_PER_SHARD,
        tables="mechanisms",
    )
    summary = curate(out, seed=11, progress=False)
    return {"out": out, "summary": summary, **read_curation(out)}


def test_curation_from_mechanisms_alone_gives_the_same_rows(
    curated_run: dict, mechanisms_only_run: dict
) -> None:
    """Simulated again, then cast to float32 as generation casts, the trajectories give the
    paths of the stored ones bit for bit: ids, points, flags and variances."""
    store = Store.open(mechanisms_only_run["out"])
    assert store.list_files("simulations") == [] and store.list_files("negatives") == []
    for table in CURATION_TABLES:
        ours, theirs = mechanisms_only_run[table], curated_run[table]
        assert ours.equals(theirs), f"{table} differs"
        ours_points = ours.column("points").combine_chunks().flatten().to_numpy()
        theirs_points = theirs.column("points").combine_chunks().flatten().to_numpy()
        assert ours_points.tobytes() == theirs_points.tobytes()
    summary, full = mechanisms_only_run["summary"], curated_run["summary"]
    assert summary["resimulated"] == MECHANISMS and full["resimulated"] == 0
    for key in ("mechanisms", "paths", "curated", "arcs", "circles", "both", "shares"):
        assert summary[key] == full[key], key


def test_mixed_root_and_chosen_tables(
    ray_cluster: str, curated_run: dict, mechanisms_only_run: dict, tmp_path: Path
) -> None:
    """Some generation shards with simulations and some without; curation writes only the
    tables asked for, and a later pass asking for others is refused in one line."""
    full, bare = Path(curated_run["out"]), Path(mechanisms_only_run["out"])
    mixed = tmp_path / "mixed"
    shutil.copytree(full, mixed, ignore=shutil.ignore_patterns(*CURATION_TABLES, "curation*"))
    store = Store.open(str(mixed))
    markers = committed_shards(store)
    without = [shard for shard in markers if shard % 2]
    for shard in without:
        (mixed / markers[shard]["files"]["simulations"]).unlink()
        # The bare run's marker, naming this root's file of the same mechanisms.
        marker = json.loads((bare / marker_file(shard)).read_text())
        marker["files"]["mechanisms"] = markers[shard]["files"]["mechanisms"]
        (mixed / marker_file(shard)).write_text(json.dumps(marker))
    assert committed_files(store, "simulations") == [
        markers[shard]["files"]["simulations"] for shard in markers if shard not in without
    ]
    moved = sum(markers[shard]["rows"]["mechanisms"] for shard in without)
    assert 0 < moved < MECHANISMS

    summary = curate(str(mixed), seed=11, progress=False, tables="curated")
    assert summary["tables"] == ["curated"] and summary["resimulated"] == moved
    rows = read_curation(str(mixed))
    assert rows["paths"] is None and rows["curated"].equals(curated_run["curated"])
    for key in ("paths", "curated", "arcs", "circles", "both", "shares"):
        assert summary[key] == curated_run["summary"][key], key
    assert {t for m in committed_shards(store, "curation").values() for t in m["files"]} == {
        "curated"
    }
    with pytest.raises(StoreError, match=r"holds another run \(tables=curated\)"):
        curate(str(mixed), seed=11, progress=False)
    refused = links(
        "curate", str(mixed), "--seed", "11", "--tables", "paths", "--address", ray_cluster
    )
    assert refused.returncode == 2
    assert refused.stderr == (
        f"links curate: error: {mixed} holds another run (tables=curated); "
        "use a new root or the same options\n"
    )

    # `paths` alone, from the same mixed shards.
    shutil.rmtree(mixed / "curated")
    shutil.rmtree(mixed / META / "curation")
    (mixed / META / "curation.json").unlink()
    summary = curate(str(mixed), seed=11, progress=False, tables=["paths"])
    rows = read_curation(str(mixed))
    assert rows["curated"] is None and rows["paths"].equals(curated_run["paths"])
    assert summary["curated"] == curated_run["summary"]["curated"]


@pytest.mark.parametrize(
    ("tables", "message"),
    [
        ("mechanisms", "tables must be among paths, curated, got 'mechanisms'"),
        (",", "tables must be among paths, curated, got '', ''"),
        ([], "tables must name at least one of paths, curated"),
    ],
)
def test_bad_curation_tables_are_refused(
    curated_run: dict, tables: str | list, message: str
) -> None:
    with pytest.raises(ValueError, match=f"^{message}$"):
        curate(curated_run["out"], seed=11, progress=False, tables=tables)
    if isinstance(tables, str):
        refused = links("curate", curated_run["out"], "--tables", tables)
        assert (refused.returncode, refused.stderr) == (2, f"links curate: error: {message}\n")


def test_paths_of_big_shards_split_their_list_arrays(
    curated_run: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A shard's paths hold no list array past the 32-bit offsets' reach: with the limit made
    small, the rows come in more, smaller arrays and batches, and are the same rows."""
    store = Store.open(curated_run["out"])
    marker = max(committed_shards(store).values(), key=lambda m: m["rows"]["mechanisms"])
    mechanisms, simulations = (
        pq.read_table(store.path(marker["files"][table])) for table in ("mechanisms", "simulations")
    )
    n = marker["n_joints"]
    whole = path_table(mechanisms, simulations, n)
    assert whole.column("points").num_chunks == 1
    limit = 7 * 200 * 2  # seven paths of 200 points
    monkeypatch.setattr(schemas, "MAX_LIST_VALUES", limit)
    monkeypatch.setattr(data_curation, "MAX_LIST_VALUES", limit)
    monkeypatch.setattr(data_curation, "MECHANISMS_PER_BATCH", 3)
    for source in (simulations, None):
        batches = list(data_curation.path_batches(mechanisms, source, n))
        assert len(batches) == -(-len(mechanisms) // 3)
        split = pa.concat_tables(batches)
        chunks = split.column("points").chunks
        assert len(chunks) >= len(batches) > 0
        assert all(len(chunk) * 400 <= limit for chunk in chunks)
        assert split.equals(whole)
    with pytest.raises(ValueError, match="8 lists of 400 values exceed the 2800 values"):
        schemas.list_array(np.zeros((8, 400), dtype=np.float32), pa.float32())


def test_curation_from_mechanisms_alone_on_s3(
    ray_cluster: str, s3_env: str, curated_run: dict
) -> None:
    uri = f"{s3_env}/links-mechanisms-only"
    generate(uri, MECHANISMS, seed=7, progress=False, topologies_per_shard=30, tables="mechanisms")
    summary = curate(uri, seed=11, progress=False, tables="curated")
    assert summary["resimulated"] == MECHANISMS
    rows = read_curation(uri)
    assert rows["paths"] is None and rows["curated"].equals(curated_run["curated"])


def test_a_lean_run_on_s3_reads_as_a_stored_one(
    ray_cluster: str, s3_env: str, curated_run: dict
) -> None:
    """`curated_run`'s plan generated as mechanisms alone on S3, curated on Ray as ids: no
    paths or simulations stored, no points; each table read derives the stored rows."""
    uri = f"{s3_env}/links-lean"
    generate(
        uri,
        MECHANISMS,
        seed=7,
        progress=False,
        topologies_per_shard=TOPOLOGIES_PER_SHARD,
        tables="mechanisms",
    )
    summary = curate(uri, seed=11, progress=False, path_store="ids")
    assert summary["path_store"] == "ids" and summary["tables"] == ["curated"]
    assert summary["curated"] == curated_run["summary"]["curated"]
    store = Store.open(uri)
    assert store.list_files("paths") == [] and store.list_files("simulations") == []
    for table in ("curated", "paths", "simulations"):
        derived = links_ray.load(uri, table, format="arrow")
        assert derived.equals(links_ray.load(curated_run["out"], table, format="arrow")), table
    with pytest.raises(ValueError, match="path_store"):  # a root holds one kind of curated set
        curate(uri, seed=11, progress=False)


def test_load_filters_and_reshapes(curated_run: dict) -> None:
    out = curated_run["out"]
    frame = links_ray.load(out, "mechanisms", n_joints=12, reshape=True)
    assert set(frame["n_joints"]) == {12} and len(frame) == 5 * TOPOLOGIES_BY_SIZE[12] == 25
    mechanisms = curated_run["mechanisms"].filter(
        pc.equal(curated_run["mechanisms"]["n_joints"], 12)
    )
    assert sorted(frame["mechanism_id"]) == sorted(mechanisms.column("mechanism_id").to_pylist())
    assert frame["positions"].iloc[0].shape == (12, 2)
    assert frame["adjacency"].iloc[0].shape == (12, 12)
    sims = links_ray.load(out, "simulations", n_joints=12, reshape=True)
    assert sims["trajectories"].iloc[0].shape == (12, 200, 2)
    table = links_ray.load(out, "paths", columns=["path_id", "is_arc"], format="arrow")
    assert table.column_names == ["path_id", "is_arc"]
    assert table.num_rows == len(curated_run["paths"])
    with pytest.raises(ValueError, match="table must be one of"):
        links_ray.load(out, "nope")
    with pytest.raises(ValueError, match="no column"):
        links_ray.load(out, "paths", columns=["nope"])


def test_stats_cli_reports_and_draws(curated_run: dict, tmp_path: Path) -> None:
    """Counts against the plan and the rows, shares counted from the rows, candidates per valid
    mechanism as measured directly with the same seed (the run used the sequential sampler, so
    `links stats --measure-candidates` measures the rejection sampler itself)."""
    plots = tmp_path / "plots"
    result = links(
        "stats", curated_run["out"], "--plots", str(plots), "--measure-candidates", "1", "--json"
    )
    assert result.returncode == 0, result.stderr
    stats = json.loads(result.stdout)
    by_size = {str(n): 5 * count for n, count in sorted(TOPOLOGIES_BY_SIZE.items())}
    assert stats["counts"]["mechanisms"] == {"rows": MECHANISMS, "by_joint_count": by_size}
    # JSON keys are strings; they come in the numbers' order all the same.
    assert list(stats["counts"]["paths"]["by_joint_count"]) == [str(n) for n in range(8, 21)]
    assert stats["counts"]["simulations"] == {"rows": MECHANISMS, "by_joint_count": by_size}
    tables = {
        "negatives": read_table(Store.open(curated_run["out"]), "negatives"),
        "paths": curated_run["paths"],
        "curated": curated_run["curated"],
    }
    for table, rows in tables.items():
        sizes = Counter(str(n) for n in rows.column("n_joints").to_pylist())
        expected = {"rows": len(rows), "by_joint_count": dict(sorted(sizes.items()))}
        assert stats["counts"][table] == expected, table
    for table in ("paths", "curated"):
        rows, shares = tables[table], stats["shares"][table]
        assert shares["paths"] == len(rows)
        for key, share in shares_of(rows).items():
            assert shares[key] == pytest.approx(share, rel=1e-12), (table, key)
        arc_only = rows.column("is_arc").to_numpy() & ~rows.column("is_circle").to_numpy()
        assert shares["arc_not_circle"] == pytest.approx(arc_only.mean(), rel=1e-12)
    measured = measure_candidates_per_valid(
        range(8, 21), 1, 5, np.random.default_rng(0), "rejection", max_candidates=200_000
    )
    assert stats["candidates_per_valid"] == {
        str(n): entry["candidates_per_valid"] for n, entry in measured.items()
    }
    assert stats["candidates_per_valid_source"].startswith("measured here")
    assert stats["candidates_per_valid_sample"]["topologies_per_joint_count"] == 1
    assert stats["paper"]["shares"] == {
        "circle": 0.34,
        "arc_not_circle": 0.28,
        "arc_or_circle": 0.62,
    }
    assert stats["paths_per_mechanism"] == len(tables["paths"]) / MECHANISMS
    angles = read_table(Store.open(curated_run["out"]), "mechanisms").column("min_transmission_deg")
    angles = angles.to_numpy()
    transmission = stats["min_transmission_deg"]
    assert transmission["mechanisms"] == MECHANISMS
    assert sum(transmission["histogram"]["counts"]) == MECHANISMS
    assert transmission["share_below"]["10"] == np.mean(angles < 10)
    assert transmission["quantiles"]["0.5"] == pytest.approx(np.median(angles))
    names = ("candidates_per_valid", "joint_counts", "curation", "mechanisms")
    assert sorted(stats["plots"]) == sorted(str(plots / f"{name}.png") for name in names)
    for name in names:
        png = plots / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000


def test_stats_cli_prints_a_short_table(curated_run: dict) -> None:
    """For a person, on a terminal or not (as here): one row per joint count, 8 to 20 in that
    order, holding the rows each table has of that size; the shares beside the paper's; a
    screenful in all. Candidates per valid are not measured unless asked: no column of them,
    a line saying how to ask."""
    result = links("stats", curated_run["out"])
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len(lines) <= 40 and max(map(len, lines)) <= 200
    header = lines.index(next(line for line in lines if line.startswith("joints")))
    names = lines[header].split()
    assert names == ["joints", "mechanisms", "simulations", "negatives", "paths", "curated"]
    assert any(line.startswith("candidates/valid: not measured (") for line in lines)
    rows = [line.split() for line in lines[header + 1 : header + 14]]
    assert [int(row[0]) for row in rows] == list(range(8, 21))
    for table in ("mechanisms", "paths", "curated"):
        column = names.index(table)
        rows_of = read_table(Store.open(curated_run["out"]), table).column("n_joints")
        sizes = Counter(rows_of.to_pylist())
        assert [int(row[column].replace(",", "")) for row in rows] == [
            sizes[n] for n in range(8, 21)
        ], table
    assert lines[header + 14].split()[:2] == ["all", str(MECHANISMS)]
    circles = next(line for line in lines if line.startswith("circles")).split()
    paths = curated_run["paths"]
    share = np.mean(paths.column("is_circle").to_numpy())
    assert circles[1] == f"{100 * share:.1f}%" and circles[2] == "34.0%"
