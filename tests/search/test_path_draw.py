"""A seeded draw of a root's curated paths (`data.path_draw`), and the retrieval index over it:
exactly the paths of smallest key, the same on a lean root as on a stored one, its rows those
of the full index, its points those stored. Made without Ray (tests/support/local_dataset.py).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import links_ray
from links_ray.data.commit import committed_files
from links_ray.data.curation import keep_draw
from links_ray.data.path_draw import MAX_DRAW_PATHS, MAX_DRAW_SEED, DrawnPaths, PathDraw
from links_ray.data.store import Store
from links_ray.search.cache import cache_folder
from links_ray.search.index import RetrievalIndex
from tests.support.local_dataset import stored_and_lean
from tests.support.results import assert_same_results

SEED, MECHANISMS, DRAWN = 5, 90, 120


@pytest.fixture(scope="module")
def roots(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    """(stored, lean): one plan written with every table, and with mechanisms and curated ids."""
    folder = str(tmp_path_factory.mktemp("draw"))
    return stored_and_lean(folder, seed=SEED, mechanisms=MECHANISMS, topologies_per_shard=3)


@pytest.fixture(scope="module")
def curated(roots: tuple[str, str]) -> dict[str, np.ndarray]:
    """The stored root's curated path ids and points, in file order."""
    table = links_ray.load(roots[0], "curated", columns=["path_id", "points"], reshape=True)
    return {
        "path_id": table["path_id"].to_numpy(),
        "points": np.stack(table["points"].to_numpy()),
    }


def smallest_keys(path_ids: np.ndarray, draw: PathDraw) -> set[int]:
    """The draw by brute force: every id sorted by its key, the first `draw.paths` kept."""
    order = np.argsort(draw.keys(path_ids), kind="stable")
    return set(path_ids[order[: draw.paths]].tolist())


def test_a_draw_holds_exactly_the_paths_of_smallest_key(
    roots: tuple[str, str], curated: dict[str, np.ndarray]
) -> None:
    ids = curated["path_id"]
    assert len(ids) > 2 * DRAWN
    store = Store.open(roots[0], writable=False)
    files = committed_files(store, "curated")
    for seed in (0, 1, MAX_DRAW_SEED):
        draw = PathDraw(DRAWN, seed)
        drawn = DrawnPaths.of(store, files, draw)
        assert drawn.rows == DRAWN
        assert set(ids[drawn.keeps(ids)].tolist()) == smallest_keys(ids, draw)
    one, other = (
        set(ids[DrawnPaths.of(store, files, PathDraw(DRAWN, s)).keeps(ids)]) for s in (0, 1)
    )
    assert one != other  # the seed decides
    # A draw of more paths than the root holds is all of them.
    assert DrawnPaths.of(store, files, PathDraw(MAX_DRAW_PATHS)).rows == len(ids)


def test_the_draw_is_apart_from_curations_own_seeded_choice(
    curated: dict[str, np.ndarray],
) -> None:
    """Curation kept arcs and circles whose keep_draw under its seed (0 here) was small; a draw
    on the same stream would favour them. Its keys are another stream."""
    ids = curated["path_id"]
    draw = PathDraw(DRAWN, 0)
    by_draw = np.argsort(draw.keys(ids))
    by_curation = np.argsort(keep_draw(ids, 0))
    assert not np.array_equal(by_draw[:DRAWN], by_curation[:DRAWN])


def test_an_index_of_a_draw_holds_the_draw_with_the_full_index_rows(
    roots: tuple[str, str], curated: dict[str, np.ndarray]
) -> None:
    stored, lean = roots
    draw = PathDraw(DRAWN, 3)
    wanted = smallest_keys(curated["path_id"], draw)
    full = RetrievalIndex.open(stored)
    on_stored = RetrievalIndex.open(stored, draw=draw)
    on_lean = RetrievalIndex.open(lean, draw=draw)
    assert len(on_stored) == DRAWN and set(on_stored.path_id.tolist()) == wanted
    # Each drawn path's sketch and mechanism are the full index's for that path.
    full_row = {path_id: row for row, path_id in enumerate(full.path_id.tolist())}
    rows = np.array([full_row[path_id] for path_id in on_stored.path_id.tolist()])
    assert np.array_equal(on_stored.sketches, full.sketches[rows])
    assert np.array_equal(on_stored.mechanism_id, full.mechanism_id[rows])
    # The lean root derives only the drawn paths' mechanisms, with the same bits.
    for name in ("path_id", "sketches", "list_start", "centroids", "file_row"):
        assert np.array_equal(getattr(on_lean, name), getattr(on_stored, name)), name
    rng = np.random.default_rng(4)
    for row in rng.choice(len(curated["points"]), size=3, replace=False):
        query = curated["points"][row] * 2.0 - 1.0
        assert_same_results(on_lean.retrieve(query, 4), on_stored.retrieve(query, 4))


def test_a_drawn_index_reads_the_drawn_points_as_stored(
    roots: tuple[str, str], curated: dict[str, np.ndarray]
) -> None:
    """`iter_points` (brute force's reader) gives the drawn paths' stored points in file
    order, on the lean root derived from a few mechanisms of each shard."""
    draw = PathDraw(DRAWN, 8)
    index = RetrievalIndex.open(roots[1], draw=draw)
    points = np.concatenate([block for _, block in index.iter_points(block=32)])
    kept = index.drawn.keeps(curated["path_id"])
    assert np.array_equal(points, curated["points"][kept])
    assert np.array_equal(np.sort(index.path_id), np.sort(curated["path_id"][kept]))
    # ...and each row's points are the ones its file row names.
    assert np.array_equal(index.paths(np.arange(5)), points[index.file_row[:5]])


def test_the_parts_of_a_drawn_index_hold_the_draw_between_them(
    roots: tuple[str, str], curated: dict[str, np.ndarray]
) -> None:
    draw = PathDraw(DRAWN, 2)
    parts = [RetrievalIndex.open(roots[1], part=part, parts=2, draw=draw) for part in range(2)]
    ids = [set(part.path_id.tolist()) for part in parts]
    assert not ids[0] & ids[1]
    assert ids[0] | ids[1] == smallest_keys(curated["path_id"], draw)


def test_a_drawn_index_is_saved_apart_from_the_full_one(roots: tuple[str, str]) -> None:
    stored = roots[0]
    store = Store.open(stored, writable=False)
    draw = PathDraw(DRAWN, 6)
    built = RetrievalIndex.open(stored, draw=draw, rebuild=True)
    assert built.build_s > 0
    full_before = store.read_json(f"{cache_folder(0, 1)}/current.json")
    loaded = RetrievalIndex.open(stored, draw=draw)
    assert loaded.build_s == 0 and np.array_equal(loaded.sketches, built.sketches)
    assert store.read_json(f"{cache_folder(0, 1, draw)}/current.json")["rows"] == DRAWN
    assert store.read_json(f"{cache_folder(0, 1)}/current.json") == full_before
    # Another seed is another draw: built, not the saved one.
    assert RetrievalIndex.open(stored, draw=PathDraw(DRAWN, 7)).build_s > 0


@pytest.mark.parametrize(
    ("paths", "seed", "named"),
    [
        (0, 0, "paths"),
        (-5, 0, "paths"),
        (True, 0, "paths"),
        (10.0, 0, "paths"),
        (MAX_DRAW_PATHS + 1, 0, "paths"),
        (10**300, 0, "paths"),
        (10, -1, "seed"),
        (10, MAX_DRAW_SEED + 1, "seed"),
        (10, "1", "seed"),
    ],
)
def test_a_bad_draw_is_refused_by_name(paths: object, seed: object, named: str) -> None:
    with pytest.raises(ValueError, match=f"the draw's {named}"):
        PathDraw(paths, seed)  # type: ignore[arg-type]


def test_links_index_builds_a_draw_and_refuses_a_bad_one(roots: tuple[str, str]) -> None:
    lean = roots[1]
    command = [sys.executable, "-m", "links_ray.cli", "index", lean, "--paths", str(DRAWN)]
    done = subprocess.run([*command, "--seed", "9"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"{DRAWN} paths (the draw of seed 9) indexed in 1 part" in done.stdout
    store = Store.open(lean, writable=False)
    saved = store.read_json(f"{cache_folder(0, 1, PathDraw(DRAWN, 9))}/current.json")
    assert saved["rows"] == DRAWN
    refused = subprocess.run(
        [*command, "--seed", "-3"], capture_output=True, text=True, timeout=300
    )
    assert refused.returncode != 0
    lines = refused.stderr.strip().splitlines()
    assert len(lines) == 1 and "the draw's seed must be in" in lines[0], refused.stderr
