"""Curation on Ray Data, the loading helper and `links stats`, on real generated data.

Every path row is checked against the definitions (docs/CONTRACT.md, Paths) from the mechanism and
simulation rows it came from; curation's kept share is checked against binomial bounds.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_cli import links
from test_generation import read_table

import links_ray
from links_ray.cluster.curation import curate
from links_ray.cluster.generation import generate
from links_ray.data.pathset import KEEP_SHARE, keep_draw
from links_ray.data.store import CURATION_TABLES, META, Store, StoreError
from links_ray.engine.paths import circle_variance, normalize_path

MECHANISMS = 300


@pytest.fixture(scope="module")
def curated_run(ray_cluster: str, tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = str(tmp_path_factory.mktemp("curation") / "data")
    generate(out, MECHANISMS, seed=7, progress=False, topologies_per_shard=4)
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
    for mechanism in curated_run["mechanisms"].to_pylist():
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
    summary = curated_run["summary"]
    assert summary["paths"] == len(paths) and summary["curated"] == len(curated)
    assert summary["shares"]["arc_or_circle"] == pytest.approx(common.mean())


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


def test_curation_on_s3_matches_local(ray_cluster: str, s3_env: str, curated_run: dict) -> None:
    uri = f"{s3_env}/links"
    generate(uri, MECHANISMS, seed=7, progress=False, topologies_per_shard=30)
    summary = curate(uri, seed=11, progress=False)
    assert summary["curated"] == len(curated_run["curated"])
    store = Store.open(uri)
    for table in CURATION_TABLES:
        assert read_table(store, table).sort_by("path_id").equals(curated_run[table])
    frame = links_ray.load(uri, "curated", n_joints=[9, 10])
    assert set(frame["n_joints"]) <= {9, 10} and len(frame) > 0


def test_load_filters_and_reshapes(curated_run: dict) -> None:
    out = curated_run["out"]
    frame = links_ray.load(out, "mechanisms", n_joints=12, reshape=True)
    assert len(frame) > 0 and set(frame["n_joints"]) == {12}
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
    plots = tmp_path / "plots"
    result = links("stats", curated_run["out"], "--plots", str(plots), "--sample-topologies", "1")
    assert result.returncode == 0, result.stderr
    stats = json.loads(result.stdout)
    assert stats["counts"]["mechanisms"]["rows"] == MECHANISMS
    assert stats["counts"]["paths"]["rows"] == len(curated_run["paths"])
    assert sum(stats["counts"]["mechanisms"]["by_joint_count"].values()) == MECHANISMS
    shares = stats["shares"]["paths"]
    assert 0 < shares["circle"] < 1 and 0 < shares["arc"] < 1
    assert shares["arc_or_circle"] <= shares["arc"] + shares["circle"]
    assert stats["shares"]["curated"]["arc_or_circle"] < shares["arc_or_circle"]
    assert set(stats["candidates_per_valid"]) == {str(n) for n in range(8, 21)}
    assert stats["paper"]["shares"]["arc_or_circle"] == 0.62
    for name in ("candidates_per_valid", "joint_counts", "curation", "mechanisms"):
        png = plots / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
