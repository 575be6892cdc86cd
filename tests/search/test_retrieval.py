"""Retrieval against exact brute force, and the returned mechanisms re-simulated in the
query's own frame."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import links_ray
from links_ray.bench.held_out import held_out_queries
from links_ray.cluster.curation import curate
from links_ray.cluster.generation import generate
from links_ray.data.store import Store
from links_ray.engine.inputs import as_max_joints, validate_query
from links_ray.engine.kinematics.mechanism import reduce_mechanism
from links_ray.engine.kinematics.paths import (
    chamfer,
    chamfer_to_many,
    normalization,
    normalize_path,
)
from links_ray.engine.kinematics.topology import grow_topology
from links_ray.engine.node_kinds import FIXED
from links_ray.search import build as search_build
from links_ray.search import cache as search_cache
from links_ray.search import kernels as kernels
from links_ray.search import query as search_query
from links_ray.search.build import _nearest_centroid, distance_fields, sketch_paths
from links_ray.search.cache import cache_folder
from links_ray.search.index import RetrievalIndex
from links_ray.search.query import _about_least, distance_table, query_variants, variant_map
from links_ray.search.reduced import reduced_joints
from tests.support.cli import links
from tests.support.results import assert_same_results


@pytest.fixture(scope="module")
def index(ray_cluster: str, tmp_path_factory: pytest.TempPathFactory) -> RetrievalIndex:
    out = str(tmp_path_factory.mktemp("retrieval") / "data")
    generate(out, 400, seed=21, progress=False, topologies_per_shard=20)
    curate(out, progress=False)
    return RetrievalIndex.open(out)


def hand_drawn(rng: np.random.Generator) -> np.ndarray:
    """A wobbly closed stroke of 40 points, as a mouse would draw a bean."""
    angle = np.linspace(0, 2 * np.pi, 40)
    radius = 1 + 0.3 * np.cos(2 * angle) + rng.normal(0, 0.01, 40)
    return np.column_stack([3 * radius * np.cos(angle) + 7, 2 * radius * np.sin(angle) - 4])


def queries() -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    return [*held_out_queries(6, seed=7), hand_drawn(rng), hand_drawn(rng)[::-1] * [-1, 1]]


def test_top3_is_exactly_the_brute_force_top3(index: RetrievalIndex) -> None:
    assert len(index) > 0
    for query in queries():
        results = index.retrieve(query, k=3)
        exact = index.brute_force(query, k=3)
        assert [r["path_id"] for r in results] == [int(index.path_id[row]) for row, _, _ in exact]
        chamfers = [r["chamfer"] for r in results]
        assert chamfers == sorted(chamfers)
        np.testing.assert_allclose(chamfers, [c for _, c, _ in exact], rtol=1e-9)


def stored_points(index: RetrievalIndex) -> np.ndarray:
    """Every path's points as the curated table stores them, in the index's row order."""
    return np.concatenate([points for _, points in index.iter_points()])[index.file_row]


def test_paths_traced_again_are_the_stored_points_bit_for_bit(index: RetrievalIndex) -> None:
    """The index keeps no points: its finalists are traced again from their mechanisms, and
    those must be exactly what curation stored."""
    stored = stored_points(index)
    assert stored.shape == (len(index), 200, 2)
    np.testing.assert_array_equal(index.paths(np.arange(len(index))), stored)
    table = links_ray.load(index.store, "mechanisms", format="arrow")
    ids = table.column("mechanism_id").to_numpy()
    for row in np.random.default_rng(1).choice(len(index.bank), 50, replace=False):
        adjacency, node_types, positions = index.bank.mechanism(row)
        stored_row = table.slice(int(np.flatnonzero(ids == index.bank.ids[row])[0]), 1)
        assert adjacency.ravel().tolist() == stored_row.column("adjacency")[0].as_py()
        assert node_types.tolist() == stored_row.column("node_types")[0].as_py()
        assert positions.ravel().tolist() == stored_row.column("positions")[0].as_py()


def test_memory_per_path_is_small(index: RetrievalIndex) -> None:
    """Sketch and mechanism row per path, and the packed mechanisms: no points (1,600 bytes a
    path) in memory."""
    basis = index.basis.mean.nbytes + index.basis.components.nbytes
    assert (index.nbytes - basis) / len(index) < 450  # the basis is the same at any size
    assert not any(
        getattr(array, "nbytes", 0) >= 1600 * len(index) for array in vars(index).values()
    )


def test_scan_brings_a_stored_path_back_in_any_frame(index: RetrievalIndex) -> None:
    """Passing only a tenth of the paths on from the scan, a stored path drawn in another
    frame still finds itself."""
    rng = np.random.default_rng(5)
    stored = stored_points(index)
    for row in rng.choice(len(index), 10, replace=False):
        angle = rng.uniform(0, 2 * np.pi)
        turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        if rng.random() < 0.5:
            turn = turn @ np.diag([1.0, -1.0])
        query = stored[row].astype(float) @ turn.T * 4.0 + [2, 3]
        normalized = normalization(query)[0]
        best_row, distance, _ = index.ranked(normalized, k=1, candidates=len(index) // 10)[0]
        assert distance < 1e-5
        assert np.allclose(stored[best_row], stored[row], atol=1e-6)


def test_brute_force_equals_every_path_against_every_variant(index: RetrievalIndex) -> None:
    """The pruned exact search against the plain one: chamfer to all paths, four variants."""
    stored = stored_points(index)
    path_ids = index.path_id
    every = index.brute_force_many(queries(), k=5)
    for query, found in zip(queries(), every, strict=True):
        normalized = normalization(query)[0]
        plain = np.stack([chamfer_to_many(v, stored) for v in query_variants(normalized)])
        best = plain.min(axis=0)
        expected = np.lexsort((path_ids, best))[:5]
        assert found == index.brute_force(query, k=5)
        assert [row for row, _, _ in found] == expected.tolist()
        np.testing.assert_allclose([c for _, c, _ in found], best[expected], rtol=1e-12)
        assert [v for _, _, v in found] == plain[:, expected].argmin(axis=0).tolist()


def test_min_transmission_keeps_the_exact_best_of_the_paths_that_keep_it(
    index: RetrievalIndex,
) -> None:
    """With `min_transmission` the answer is the plain brute force over only the curated
    paths whose stored angle reaches it; each result says its angle."""
    curated = links_ray.load(index.store, "curated", columns=["path_id", "min_transmission_deg"])
    angle_of = dict(zip(curated["path_id"], curated["min_transmission_deg"], strict=True))
    angles = np.array([angle_of[int(p)] for p in index.path_id])
    np.testing.assert_array_equal(index.transmission, angles)
    floor = float(np.quantile(angles, 0.7))
    keeps = angles >= floor
    stored = stored_points(index)
    path_ids = index.path_id
    for query in queries():
        results = index.retrieve(query, k=5, min_transmission=floor)
        normalized = normalization(query)[0]
        plain = np.stack([chamfer_to_many(v, stored) for v in query_variants(normalized)])
        best = np.where(keeps, plain.min(axis=0), np.inf)
        expected = np.lexsort((path_ids, best))[:5]
        assert [r["path_id"] for r in results] == path_ids[expected].tolist()
        np.testing.assert_allclose([r["chamfer"] for r in results], best[expected], rtol=1e-9)
        assert all(r["min_transmission_deg"] >= floor for r in results)
    # A floor no path reaches gives no results; a bad one a clear error.
    above_all = float(angles.max()) + 1.0
    assert index.ranked(normalization(queries()[0])[0], 3, min_transmission=above_all) == []
    with pytest.raises(ValueError, match="min_transmission must be from 0 to 45 degrees"):
        index.retrieve(queries()[0], k=3, min_transmission=60)


def test_reduced_joint_counts_are_those_of_the_reduced_mechanisms(index: RetrievalIndex) -> None:
    """Every path's count, from the packed solution paths, is the size of the mechanism
    `reduce_mechanism` makes of its stored mechanism and joint."""
    table = links_ray.load(index.store, "mechanisms", format="arrow")
    by_id = {int(m): i for i, m in enumerate(table.column("mechanism_id").to_numpy())}
    adjacency, node_types = table.column("adjacency"), table.column("node_types")
    expected = []
    for mechanism_id, joint in zip(index.mechanism_id, index.joint, strict=True):
        i = by_id[int(mechanism_id)]
        types = np.array(node_types[i].as_py())
        graph = np.array(adjacency[i].as_py()).reshape(len(types), len(types))
        reduced = reduce_mechanism(graph, types, np.zeros((len(types), 2)), int(joint))
        expected.append(len(reduced[1]))
    np.testing.assert_array_equal(index.n_joints, expected)
    assert len(np.unique(expected)) >= 5  # simple and complex mechanisms alike


def test_max_joints_keeps_the_exact_best_of_the_simple_paths(index: RetrievalIndex) -> None:
    """With `max_joints` the answer is the plain brute force over only the paths whose
    reduced mechanism has that many joints or fewer, with `min_transmission` too; each result
    says its reduced mechanism's joints."""
    counts = index.n_joints
    most = int(np.median(counts))
    keeps = counts <= most
    assert 0.2 < keeps.mean() < 0.9
    floor = float(np.quantile(index.transmission, 0.5))
    stored = stored_points(index)
    path_ids = index.path_id
    for query in queries():
        normalized = normalization(query)[0]
        plain = np.stack([chamfer_to_many(v, stored) for v in query_variants(normalized)])
        for allowed, options in [
            (keeps, {"max_joints": most}),
            (
                keeps & (index.transmission >= floor),
                {"max_joints": most, "min_transmission": floor},
            ),
        ]:
            results = index.retrieve(query, k=5, **options)
            best = np.where(allowed, plain.min(axis=0), np.inf)
            expected = np.lexsort((path_ids, best))[:5]
            assert [r["path_id"] for r in results] == path_ids[expected].tolist()
            np.testing.assert_allclose([r["chamfer"] for r in results], best[expected], rtol=1e-9)
            for result in results:
                assert result["n_joints"] == len(result["mechanism"]["node_types"]) <= most
        # Unrestricted, the best is a larger mechanism than allowed for some of the queries.
    unrestricted = [index.retrieve(q, k=1)[0]["n_joints"] for q in queries()]
    assert max(unrestricted) > most
    # A limit below every path's count gives no results; a bad one a clear error.
    assert index.ranked(normalization(queries()[0])[0], 3, max_joints=int(counts.min()) - 1) == []
    with pytest.raises(ValueError, match="max_joints must be from 2 to 20, got 21"):
        index.retrieve(queries()[0], k=3, max_joints=21)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (1, "max_joints must be from 2 to 20, got 1"),
        (21, "max_joints must be from 2 to 20, got 21"),
        (True, "max_joints must be an integer from 2 to 20, got True"),
        (6.0, "max_joints must be an integer from 2 to 20, got 6.0"),
        ("6", "max_joints must be an integer from 2 to 20, got '6'"),
    ],
)
def test_bad_max_joints_are_refused(value: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        as_max_joints(value)


def test_max_joints_takes_none_and_the_dataset_range() -> None:
    assert as_max_joints(None) is None
    assert [as_max_joints(j) for j in (2, np.int64(8), 20)] == [2, 8, 20]


def test_reduced_joints_of_grown_topologies_match_reduce_mechanism() -> None:
    """The kernel over mechanisms of every dataset size, each joint of each, against
    `reduce_mechanism`."""
    rng = np.random.default_rng(4)
    topologies = [grow_topology(rng, n) for n in range(5, 21) for _ in range(3)]
    orders = [t.order.astype(np.uint8) for t in topologies]
    order_start = np.cumsum([0] + [len(o) for o in orders])
    joint_start = np.cumsum([0] + [t.n_joints for t in topologies])
    mechanisms, joints, expected = [], [], []
    for m, topology in enumerate(topologies):
        for joint in np.flatnonzero(topology.node_types != FIXED):
            reduced = reduce_mechanism(
                topology.adjacency,
                topology.node_types,
                np.zeros((topology.n_joints, 2)),
                int(joint),
            )
            mechanisms.append(m)
            joints.append(joint)
            expected.append(len(reduced[1]))
    out = np.empty(len(joints), dtype=np.int16)
    reduced_joints(
        np.concatenate(orders),
        order_start,
        joint_start,
        np.array(mechanisms),
        np.array(joints),
        out,
    )
    np.testing.assert_array_equal(out, expected)
    assert min(expected) == 2 and max(expected) == 20


def test_finalists_are_measured_as_if_every_variant_were(index: RetrievalIndex) -> None:
    """Measuring each finalist's likeliest variant, then only the variants its lower bound
    leaves able to matter, gives the answer of measuring all four."""
    rng = np.random.default_rng(12)
    stored = stored_points(index)
    for query in queries():
        normalized = normalization(query)[0]
        variants = query_variants(normalized)
        rows = rng.choice(len(index), 40, replace=False)
        plain = np.stack([chamfer_to_many(v, stored[rows]) for v in variants])
        best = plain.min(axis=0)
        expected = np.lexsort((index.path_ids(rows), best))[:5]
        # The likeliest variant given right, at random, and as the worst of the four.
        for likely in (plain.argmin(axis=0), rng.integers(0, 4, 40), plain.argmax(axis=0)):
            found = search_query.exact_finalists(
                index.arrays, variants, distance_table(normalized)[0], rows, likely, k=5
            )
            assert [row for row, _, _ in found] == rows[expected].tolist()
            np.testing.assert_allclose([c for _, c, _ in found], best[expected], rtol=1e-12)
            assert [v for _, _, v in found] == plain[:, expected].argmin(axis=0).tolist()


def test_path_to_query_bounds_never_exceed_the_true_distance() -> None:
    rng = np.random.default_rng(11)
    query = normalize_path(np.cumsum(rng.normal(size=(150, 2)), axis=0))
    paths = np.stack(
        [normalize_path(np.cumsum(rng.normal(size=(200, 2)), axis=0)) for _ in range(40)]
    )
    on_query = query[np.linspace(0, len(query) - 1, 200).round().astype(int)]
    paths = np.concatenate([paths, on_query[None]]).astype(np.float32)  # lies on the query
    table, _ = distance_table(query)
    bounds = np.empty((len(paths), 4))
    cell = (kernels.TABLE_HI - kernels.TABLE_LO) / kernels.TABLE_CELLS
    kernels.path_to_query_bounds(table, paths, bounds)
    for variant, (matrix, offset) in enumerate(map(variant_map, range(4))):
        moved = query @ matrix.T + offset
        for p, path in enumerate(paths.astype(np.float64)):
            nearest = np.sqrt(((path[:, None] - moved[None]) ** 2).sum(-1)).min(axis=1).mean()
            assert bounds[p, variant] <= nearest + 1e-12
            assert bounds[p, variant] >= nearest - 2 * cell  # and tight
    assert bounds[-1, 0] < 1e-6


def test_bounds_of_many_queries_never_exceed_the_true_distance() -> None:
    """`nearest_node_bounds`, for brute force: every query at once, from the nearest node."""
    rng = np.random.default_rng(13)
    queries = [normalize_path(np.cumsum(rng.normal(size=(120, 2)), axis=0)) for _ in range(5)]
    paths = np.stack(
        [normalize_path(np.cumsum(rng.normal(size=(200, 2)), axis=0)) for _ in range(30)]
    ).astype(np.float32)
    nodes = 257
    tables = np.empty((nodes, nodes, len(queries)), dtype=np.float32)
    for q, query in enumerate(queries):
        table = np.empty((nodes, nodes))
        kernels.distance_table(query, table, np.empty((nodes, nodes), dtype=np.int32))
        tables[:, :, q] = table
    bounds = np.empty((len(paths), 4, len(queries)), dtype=np.float32)
    kernels.nearest_node_bounds(tables, paths, bounds)
    reach = (kernels.TABLE_HI - kernels.TABLE_LO) / (nodes - 1) / np.sqrt(2)
    for q, query in enumerate(queries):
        for variant, (matrix, offset) in enumerate(map(variant_map, range(4))):
            moved = query @ matrix.T + offset
            for p, path in enumerate(paths.astype(np.float64)):
                nearest = np.sqrt(((path[:, None] - moved[None]) ** 2).sum(-1)).min(axis=1).mean()
                assert bounds[p, variant, q] <= nearest + 1e-5
                assert bounds[p, variant, q] >= nearest - 2 * reach  # and tight
    # The other half from a sample of a query's points: their summed distances to the path.
    sample = queries[0][::7]
    rows, variants = np.repeat(np.arange(len(paths)), 4), np.tile(np.arange(4), len(paths))
    sums = np.empty(len(rows))
    kernels.sample_to_path_sums(sample, paths, rows, variants, sums)
    for row, variant, total in zip(rows, variants, sums, strict=True):
        matrix, offset = variant_map(variant)
        moved = sample @ matrix.T + offset
        path = paths[row].astype(np.float64)
        expected = np.sqrt(((moved[:, None] - path[None]) ** 2).sum(-1)).min(axis=1).sum()
        assert total == pytest.approx(expected, rel=1e-9)


def test_returned_mechanism_traces_the_query_where_it_was_drawn(index: RetrievalIndex) -> None:
    for query in queries():
        i, j = links_ray.engine.kinematics.paths.longest_chord(query)
        chord = np.linalg.norm(query[j] - query[i])
        results = index.retrieve(query, k=3)
        assert len(results) == 3
        for result in results:
            mechanism = result["mechanism"]
            traced = links_ray.simulate(
                mechanism["adjacency"], mechanism["node_types"], mechanism["positions"]
            )[result["mechanism_joint"]]
            # Chamfer scales with the frame: the normalized distance times the query's chord.
            assert chamfer(traced, query) == pytest.approx(result["chamfer"] * chord, rel=1e-4)
            full = links_ray.load(index.store, "mechanisms", columns=["mechanism_id", "node_types"])
            stored = full[full.mechanism_id == result["mechanism_id"]].iloc[0]
            assert len(mechanism["node_types"]) <= len(stored.node_types)
            assert result["path_id"] == 32 * result["mechanism_id"] + result["joint"]
            assert np.array(result["points"]).shape == (200, 2)


@pytest.mark.parametrize(
    ("points", "k", "message"),
    [
        ([[0, 0], [1, 1]], 3, "points must hold 3 to 10000 pairs, got 2"),
        ([[0, 0]] * 10_001, 3, "points must hold 3 to 10000 pairs, got 10001"),
        ([], 3, "points must hold 3 to 10000 pairs, got 0"),
        ([[1, 1]] * 5, 3, "points are all the same point: there is no curve"),
        ([[0, 0], [1, float("nan")], [2, 2]], 3, "points must be finite numbers"),
        ([[0, 0], [1, 1e13], [2, 2]], 3, r"points must lie within \+-1e\+12"),
        ([[0, 0], [1e-10, 0], [0, 1e-10]], 3, "points span less than 1e-09"),
        ([[0, 0], [1, 1], [2, 2]], 0, "k must be from 1 to 100, got 0"),
        ([[0, 0], [1, 1], [2, 2]], 101, "k must be from 1 to 100, got 101"),
        ([[0, 0], [1, 1], [2, 2]], True, "k must be an integer from 1 to 100, got True"),
        ([[0, 0], [1, 1, 1], [2, 2]], 3, r"points must be a list of \[x, y\] number pairs"),
        ("zigzag", 3, r"points must be a list of \[x, y\] number pairs"),
        ([[0, 0, 0], [1, 1, 1], [2, 2, 2]], 3, r"points must be \[x, y\] pairs, got an array"),
    ],
)
def test_bad_queries_are_refused(points: object, k: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        validate_query(points, k)


def test_coarse_lists_group_rows_and_probing_finds_the_near_ones(
    index: RetrievalIndex, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """With lists of about 100 rows, rows are grouped by the list of their nearest centroid;
    a query scanning only its nearest lists (a quarter of the rows) still finds a stored path
    drawn in another frame, and scanning all lists answers as the index without lists."""
    monkeypatch.setattr(search_build, "ROWS_PER_LIST", 100)
    monkeypatch.setitem(search_cache.BUILD_SETTINGS, "rows_per_list", 100)
    copy = tmp_path / "data"  # its saved index is built otherwise: keep the fixture's
    shutil.copytree(index.store.uri, copy)
    lists = RetrievalIndex.open(str(copy))
    assert lists.build_s > 0
    count = len(lists.centroids)
    assert count == len(index) // 100
    assert sorted(lists.file_row.tolist()) == list(range(len(index)))
    sizes = np.diff(lists.list_start)
    assert lists.list_start[0] == 0 and lists.list_start[-1] == len(index) and sizes.min() >= 0
    stored = stored_points(index)
    fields = distance_fields(stored_points(lists), search_build.FIELD_STRIDE)
    np.testing.assert_array_equal(
        _nearest_centroid(lists.basis.field_codes(fields), lists.centroids),
        np.repeat(np.arange(count), sizes),
    )
    np.testing.assert_array_equal(lists.paths(np.arange(len(lists))), stored_points(lists))
    # Every list scanned: the same answers as the index of one list.
    for query in queries():
        assert_same_results(lists.retrieve(query, k=5), index.retrieve(query, k=5))
    # A quarter of the rows scanned, a fifth of those passed on: a stored path finds itself.
    # (Not a tenth: the sketches barely tell apart the many near-straight paths, a few
    # hundredths wide, so one of those can rank 30th among its look-alikes.)
    monkeypatch.setattr(search_query, "PROBED_ROWS", len(index) // 4)
    rng = np.random.default_rng(6)
    path_ids = lists.path_id
    for row in rng.choice(len(index), 10, replace=False):
        angle = rng.uniform(0, 2 * np.pi)
        turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        query = stored[row].astype(float) @ turn.T * 3.0 - [1, 2]
        field_codes = lists.basis.query(query_variants(normalization(query)[0]))
        starts, ends, _ = lists.probe(field_codes, len(index) // 4)
        assert len(index) // 4 <= (ends - starts).sum() < len(index) // 2
        best = lists.ranked(normalization(query)[0], k=1, candidates=len(index) // 20)[0]
        assert best[1] < 1e-5
        assert np.allclose(stored_points(lists)[best[0]], stored[row], atol=1e-6)
        assert path_ids[best[0]] in index.path_id


def test_saved_index_is_reused(index: RetrievalIndex) -> None:
    assert Store.open(index.store.uri).read_json(f"{cache_folder(0, 1)}/current.json")
    again = RetrievalIndex.open(index.store.uri)
    for name in search_cache.ROW_ARRAYS:
        np.testing.assert_array_equal(getattr(again, name), getattr(index, name))
    for name, array in index.bank.arrays().items():
        np.testing.assert_array_equal(getattr(again.bank, name), array)
    np.testing.assert_array_equal(again.basis.components, index.basis.components)
    assert again.build_s == 0.0, "loaded, not rebuilt"


def test_parts_split_the_paths_by_curation_shard(index: RetrievalIndex) -> None:
    """Parts of an index hold its paths once each, the shards numbered part modulo parts,
    and answer with exactly the distances the whole index measures."""
    parts = [RetrievalIndex.open(index.store, part=p, parts=3) for p in range(3)]
    ids = np.concatenate([part.path_id for part in parts])
    assert sorted(ids.tolist()) == sorted(index.path_id.tolist())
    for p, part in enumerate(parts):
        assert part.files and all(int(f.rsplit("shard-", 1)[1][:6]) % 3 == p for f in part.files)
        assert Store.open(index.store.uri).read_json(f"{cache_folder(p, 3)}/current.json")
    for query in queries():
        whole = {r["path_id"]: r["chamfer"] for r in index.retrieve(query, k=10)}
        shared = 0
        for part in parts:
            for result in part.retrieve(query, k=10):
                if result["path_id"] in whole:
                    assert result["chamfer"] == whole[result["path_id"]]
                    shared += 1
        assert shared == len(whole)  # the whole index's ten best are each some part's
    with pytest.raises(ValueError, match=r"part must be in 0\.\.parts-1"):
        RetrievalIndex.open(index.store, part=3, parts=3)


def test_warm_up_is_bounded_and_leaves_answers_unchanged(index: RetrievalIndex) -> None:
    query = hand_drawn(np.random.default_rng(5))
    before = index.retrieve(query, k=5)
    assert index.warm(seconds=60, queries=7) == 7
    assert index.warm(seconds=0, queries=100) == 1, "the first query is always answered"
    assert_same_results(index.retrieve(query, k=5), before)
    with pytest.raises(ValueError, match="queries >= 1"):
        index.warm(queries=0)


def test_offline_cli(index: RetrievalIndex, tmp_path: Path) -> None:
    query = tmp_path / "query.json"
    query.write_text(json.dumps({"points": hand_drawn(np.random.default_rng(1)).tolist()}))
    result = links("retrieve", index.store.uri, "--points", str(query), "-k", "2", "--json")
    assert result.returncode == 0, result.stderr
    answer = json.loads(result.stdout)
    assert len(answer["results"]) == 2 and answer["took_ms"] > 0
    # Read by a script (not a terminal): JSON without asking, as the contract says.
    piped = links("retrieve", index.store.uri, "--points", str(query), "-k", "2")
    assert [r["path_id"] for r in json.loads(piped.stdout)["results"]] == [
        r["path_id"] for r in answer["results"]
    ]
    # For a person: a title, a header, one row a result (its path id and chamfer), a footnote.
    result = links("retrieve", index.store.uri, "--points", str(query), "-k", "2", "--table")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len(lines) == 5 and len(result.stdout) < 600
    assert lines[0].startswith("2 paths in ")
    header = lines[1].split()
    for rank, (line, expected) in enumerate(zip(lines[2:4], answer["results"], strict=True), 1):
        row = dict(zip(header, line.split(), strict=True))
        assert row["rank"] == str(rank)
        assert row["path"] == str(expected["path_id"])
        assert row["mechanism"] == str(expected["mechanism_id"])
        assert row["chamfer"] == f"{expected['chamfer']:.4f}"
    bad = tmp_path / "bad.json"
    bad.write_text("[[0, 0], [1, 1]]")
    result = links("retrieve", index.store.uri, "--points", str(bad))
    assert result.returncode == 2
    assert result.stderr == "links retrieve: error: points must hold 3 to 10000 pairs, got 2\n"
    # Kept to simple mechanisms: the index's own answer, each result within the limit.
    most = int(np.median(index.n_joints))
    result = links(
        "retrieve", index.store.uri, "--points", str(query), "-k", "3", "--max-joints", str(most)
    )
    assert result.returncode == 0, result.stderr
    simple = json.loads(result.stdout)["results"]
    drawn = hand_drawn(np.random.default_rng(1))
    expected = index.retrieve(drawn, k=3, max_joints=most)
    assert [r["path_id"] for r in simple] == [r["path_id"] for r in expected]
    assert len(simple) == 3 and all(r["n_joints"] <= most for r in simple)
    for value, message in [
        ("1", "max_joints must be from 2 to 20, got 1"),
        ("21", "max_joints must be from 2 to 20, got 21"),
    ]:
        result = links("retrieve", index.store.uri, "--points", str(query), "--max-joints", value)
        assert result.returncode == 2
        assert result.stderr == f"links retrieve: error: {message}\n"
    result = links("retrieve", index.store.uri, "--points", str(query), "--max-joints", "six")
    assert result.returncode == 2
    assert len(result.stderr.splitlines()) == 1 and "--max-joints" in result.stderr


def test_sketch_scan_is_the_mean_distance_of_its_points_in_the_best_variants() -> None:
    """The scan's score is the least over the variants of the mean of the level table at the
    chosen sketch points, the variant flipped as `variant_map` flips it; with the second
    variant passed on exactly when within the margin."""
    rng = np.random.default_rng(2)
    query = smooth_paths(rng, 1)[0].astype(np.float64)
    _, owners = distance_table(query)
    levels = np.empty((kernels.SKETCH_LEVELS + 1,) * 2, dtype=np.float32)
    kernels.level_table(query, owners, levels)
    sketches = sketch_paths(smooth_paths(rng, 5000))
    slots = kernels.scan_slots(16)
    # Two row ranges of uneven length, cut into pieces: scores packed in range order.
    starts, ends = np.array([3000, 100]), np.array([5000, 1337])
    pieces = kernels.scan_pieces(starts, ends, piece=300)
    assert (pieces[1] - pieces[0]).max() == 300
    scores = np.empty(2000 + 1237, dtype=np.float32)
    likely = np.empty(len(scores), dtype=np.int8)
    margin = 0.01
    kernels.sketch_scan(sketches, *pieces, levels, slots, margin, scores, likely)
    rows = np.r_[3000:5000, 100:1337]
    # In numpy: each slot's point, in each variant, looked up at its own level coordinates.
    xs = sketches[rows][:, slots].astype(np.float64) / kernels.SKETCH_LEVELS
    ys = sketches[rows][:, kernels.SKETCH_POINTS + slots].astype(np.float64)
    ys /= kernels.SKETCH_LEVELS
    means = np.empty((len(rows), 4))
    for variant in range(4):
        matrix, offset = variant_map(variant)
        x = np.rint((matrix[0, 0] * xs + offset[0]) * kernels.SKETCH_LEVELS).astype(int)
        y = np.rint((matrix[1, 1] * ys + offset[1]) * kernels.SKETCH_LEVELS).astype(int)
        means[:, variant] = levels[x, y].mean(axis=1)
    np.testing.assert_allclose(scores, means.min(axis=1), rtol=1e-5)
    order = np.argsort(means, axis=1)
    ranked = np.sort(means, axis=1)
    gap = ranked[:, 1] - ranked[:, 0]
    # Rows whose order float32 sums cannot flip.
    clear = (gap > 1e-5) & (np.abs(gap - margin) > 1e-5) & (ranked[:, 2] - ranked[:, 1] > 1e-5)
    first, second = likely // 4, likely % 4
    assert clear.sum() > 1000
    assert (first[clear] == order[clear, 0]).all()
    near = gap < margin
    assert (second[clear & near] == order[clear & near, 1]).all()
    assert (second[clear & ~near] == first[clear & ~near]).all()
    assert 0 < (clear & near).sum() < clear.sum()  # both cases occur
    # Every eighth point in time: the even ones, stored first.
    np.testing.assert_array_equal(slots, np.arange(0, 64, 4))
    with pytest.raises(ValueError, match="scan points must divide 64"):
        kernels.scan_slots(3)


def test_selection_keeps_about_the_least_values() -> None:
    rng = np.random.default_rng(4)
    values = rng.normal(size=100_000).astype(np.float32)
    for count in (500, 5_000, 20_000, 60_000):
        chosen = _about_least(values, count)
        assert (np.diff(chosen) > 0).all()
        # Exactly the values up to a threshold: none left out below the largest chosen.
        assert set(chosen.tolist()) == set(np.flatnonzero(values <= values[chosen].max()))
        assert abs(len(chosen) - count) < 0.1 * count
    assert _about_least(values, 100_000).tolist() == list(range(100_000))
    few = values[:500]  # too few to sample: exactly the least
    assert _about_least(few, 7).tolist() == sorted(np.argsort(few)[:7].tolist())


def smooth_paths(rng: np.random.Generator, count: int) -> np.ndarray:
    """Normalized closed curves of 200 points with a few random harmonics each."""
    angle = np.linspace(0, 2 * np.pi, 200)
    paths = []
    for _ in range(count):
        a, b = rng.normal(size=(2, 4)) / np.arange(1, 5)
        curve = np.column_stack(
            [
                sum(a[h] * np.cos((h + 1) * angle + h) for h in range(4)),
                sum(b[h] * np.sin((h + 1) * angle - h) for h in range(4)),
            ]
        )
        paths.append(normalize_path(curve))
    return np.stack(paths).astype(np.float32)


def every_pair(
    rng: np.random.Generator, count: int, noise: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`count` paths, the first 20 of them the query plus noise, so that the best matches are
    close ones; every (path, variant) pair as rows and variants; their exact distances."""
    paths = smooth_paths(rng, count)
    query = smooth_paths(rng, 1)[0].astype(np.float64)
    paths[:20] = np.clip(query + rng.normal(0, noise, (20, 200, 2)), 0, 1)
    rows = np.repeat(np.arange(count), 4)
    variants = np.tile(np.arange(4), count)
    exact = np.stack([chamfer_to_many(v, paths) for v in query_variants(query)]).T.ravel()
    return paths, query, rows, variants, exact


def test_sketches_hold_evenly_spaced_points_to_half_a_level() -> None:
    paths = smooth_paths(np.random.default_rng(8), 50)
    sketches = sketch_paths(paths)
    assert sketches.shape == (50, 2 * kernels.SKETCH_POINTS) and sketches.dtype == np.uint8
    times = np.linspace(0, 199, kernels.SKETCH_POINTS).round().astype(int)
    # Even points first: the leading half is a sketch of its own.
    times = np.concatenate([times[0::2], times[1::2]])
    decoded = sketches.reshape(50, 2, -1).transpose(0, 2, 1) / kernels.SKETCH_LEVELS
    assert np.abs(decoded - paths[:, times]).max() <= 0.5 / kernels.SKETCH_LEVELS + 1e-6


def test_rough_estimate_follows_the_exact_chamfer_distance() -> None:
    """The sketch estimate of every (path, variant) pair: close to the exact distance, and
    ranking pairs nearly as the exact distance does."""
    paths, query, rows, variants, exact = every_pair(np.random.default_rng(9), 300, 0.01)
    levels = np.empty((kernels.SKETCH_LEVELS + 1,) * 2, dtype=np.float32)
    kernels.level_table(query, distance_table(query)[1], levels)
    sketches = sketch_paths(paths)
    picked = query[np.linspace(0, 199, kernels.ROUGH_SAMPLE).round().astype(int)]
    sample = np.rint(picked * kernels.SKETCH_LEVELS).astype(np.int32)
    rough = np.empty(len(rows))
    none = np.empty(0, dtype=np.int32)
    kernels.sketch_chamfer(
        sample, levels, sketches, rows, variants, kernels.ROUGH_POINTS, none, rough
    )
    assert np.abs(rough - exact).max() < 0.03
    assert np.abs(rough - exact).mean() < 0.008
    best = set(np.argsort(exact)[:40])
    assert len(best & set(np.argsort(rough)[:80])) >= 38
    # The whole sketch, from more query points, follows the exact distance more closely.
    picked = query[np.linspace(0, 199, 32).round().astype(int)]
    sample = np.rint(picked * kernels.SKETCH_LEVELS).astype(np.int32)
    fine = np.empty(len(rows))
    midpoints = kernels.sketch_midpoints(200)
    kernels.sketch_chamfer(
        sample, levels, sketches, rows, variants, kernels.SKETCH_POINTS, midpoints, fine
    )
    assert np.abs(fine - exact).mean() < 0.6 * np.abs(rough - exact).mean()
    assert len(best & set(np.argsort(fine)[:60])) >= 39


def test_level_table_is_the_distance_from_each_level() -> None:
    query = smooth_paths(np.random.default_rng(10), 1)[0].astype(np.float64)
    table, owners = distance_table(query)
    levels = np.empty((kernels.SKETCH_LEVELS + 1,) * 2, dtype=np.float32)
    kernels.level_table(query, owners, levels)
    grid = np.arange(kernels.SKETCH_LEVELS + 1) / kernels.SKETCH_LEVELS
    nodes = np.stack(np.meshgrid(grid, grid, indexing="ij"), axis=-1).reshape(-1, 2)
    exact = np.sqrt(((nodes[:, None] - query[None]) ** 2).sum(-1)).min(axis=1)
    found = levels.ravel().astype(np.float64)
    assert (found >= exact - 1e-6).all()  # the distance to some query point: never less
    # Exact nearly everywhere, and close everywhere.
    assert np.mean(np.abs(found - exact) < 1e-6) > 0.98
    assert np.abs(found - exact).max() < 0.01
    # The table holds the exact distance at its nodes, and which query point is nearest.
    size = (kernels.TABLE_HI - kernels.TABLE_LO) / kernels.TABLE_CELLS
    node = np.array([40, 77])
    at = kernels.TABLE_LO + node * size
    distances = np.sqrt(((query - at) ** 2).sum(axis=1))
    assert table[tuple(node)] == pytest.approx(distances.min())
    assert owners[tuple(node)] == distances.argmin()


def test_fine_estimate_is_near_the_exact_chamfer_distance() -> None:
    """From the whole sketch, its midpoints and 32 query points, close pairs are estimated to
    within the sketch's rounding, and closer than from the sketch's points alone."""
    paths, query, rows, variants, exact = every_pair(np.random.default_rng(12), 200, 0.005)
    levels = np.empty((kernels.SKETCH_LEVELS + 1,) * 2, dtype=np.float32)
    kernels.level_table(query, distance_table(query)[1], levels)
    picked = query[np.linspace(0, 199, 32).round().astype(int)]
    sample = np.rint(picked * kernels.SKETCH_LEVELS).astype(np.int32)
    sketches = sketch_paths(paths)
    estimates = {}
    for name, midpoints in (
        ("with", kernels.sketch_midpoints(200)),
        ("without", np.empty(0, dtype=np.int32)),
    ):
        estimates[name] = np.empty(len(rows))
        kernels.sketch_chamfer(
            sample,
            levels,
            sketches,
            rows,
            variants,
            kernels.SKETCH_POINTS,
            midpoints,
            estimates[name],
        )
    estimate = estimates["with"]
    close = exact < 0.05
    assert close.sum() >= 20
    assert np.abs(estimate - exact)[close].max() < 0.004
    assert np.abs(estimate - exact).max() < 0.02
    # The sketch's points alone stand further from the path's 200: they overstate it.
    error = {name: np.abs(value - exact)[close].mean() for name, value in estimates.items()}
    assert error["with"] < 0.7 * error["without"], error


def test_sketch_midpoints_fill_the_gaps_of_the_sketch() -> None:
    """At 200 steps the sketch's 128 points skip 72 of the path's; a midpoint stands in for
    each, so the estimate sees 200 points. A path of no more points than the sketch has none."""
    midpoints = kernels.sketch_midpoints(200)
    times = np.floor(np.arange(kernels.SKETCH_POINTS) * 199 / 127 + 0.5).astype(int)
    assert len(midpoints) == 200 - kernels.SKETCH_POINTS
    assert (times[midpoints + 1] - times[midpoints] == 2).all()
    assert len(kernels.sketch_midpoints(100)) == 0
