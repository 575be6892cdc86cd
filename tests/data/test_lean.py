"""A lean root (mechanisms, and the curated set as ids) reads as a root that stores every
table: each derived row equal bit for bit to the stored one of the same run, the index built
on it equal, at a fraction of the bytes. Made without Ray (tests/support/local_dataset.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import links_ray
from links_ray.data.commit import ShardWriter, committed_files
from links_ray.data.derived import derived_tables
from links_ray.data.schemas import SCHEMAS
from links_ray.data.store import Store
from links_ray.search.index import RetrievalIndex
from tests.support.local_dataset import stored_and_lean
from tests.support.results import assert_same_results

SEED, MECHANISMS = 11, 60


@pytest.fixture(scope="module")
def roots(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    """(stored, lean): one plan written with every table, and with mechanisms and curated ids."""
    folder = str(tmp_path_factory.mktemp("lean"))
    return stored_and_lean(folder, seed=SEED, mechanisms=MECHANISMS, topologies_per_shard=3)


def folder_bytes(root: str, table: str) -> int:
    return sum(p.stat().st_size for p in Path(root, table).rglob("*.parquet"))


def test_the_lean_root_stores_ids_and_derives_the_rest(roots: tuple[str, str]) -> None:
    stored, lean = roots
    assert derived_tables(Store.open(stored, writable=False)) == ()
    assert derived_tables(Store.open(lean, writable=False)) == ("simulations", "paths", "curated")
    (first,) = committed_files(Store.open(lean, writable=False), "curated")[:1]
    assert "points" not in pq.read_schema(Path(lean, first)).names
    # The curated ids take a small share of the bytes of the curated points.
    assert folder_bytes(lean, "curated") * 10 < folder_bytes(stored, "curated")
    assert not Path(lean, "simulations").exists() and not Path(lean, "paths").exists()


@pytest.mark.parametrize("table", ["curated", "paths", "simulations"])
def test_derived_rows_equal_stored_rows_bit_for_bit(roots: tuple[str, str], table: str) -> None:
    stored, lean = roots
    expected = links_ray.load(stored, table, format="arrow")
    derived = links_ray.load(lean, table, format="arrow")
    assert derived.schema == expected.schema
    assert len(expected) > 0 and derived.equals(expected)


def test_a_read_by_joint_count_and_columns_and_split_agrees(roots: tuple[str, str]) -> None:
    stored, lean = roots
    sizes = sorted(set(links_ray.load(stored, "mechanisms", columns=["n_joints"])["n_joints"]))
    some = sizes[: max(1, len(sizes) // 2)]
    for columns in (["path_id", "points"], ["path_id", "is_circle"]):
        expected = links_ray.load(stored, "curated", n_joints=some, columns=columns)
        got = links_ray.load(lean, "curated", n_joints=some, columns=columns)
        assert len(got) > 0
        assert got.equals(expected)
    for split in ("train", "test"):
        expected = links_ray.load(stored, "paths", columns=["path_id", "points"], split=split)
        assert links_ray.load(lean, "paths", columns=["path_id", "points"], split=split).equals(
            expected
        )
    frame = links_ray.load(lean, "curated", columns=["points"], reshape=True)
    assert frame["points"].iloc[0].shape == (200, 2)


def test_an_index_on_the_lean_root_answers_as_on_the_stored_one(roots: tuple[str, str]) -> None:
    stored, lean = roots
    on_stored, on_lean = RetrievalIndex.open(stored), RetrievalIndex.open(lean)
    assert len(on_lean) == len(on_stored) > 0
    rng = np.random.default_rng(3)
    curated = links_ray.load(stored, "curated", columns=["points"], reshape=True)
    for row in rng.choice(len(curated), size=4, replace=False):
        query = curated["points"].iloc[row] * 3.0 + 1.0
        assert_same_results(on_lean.retrieve(query, 5), on_stored.retrieve(query, 5))


def test_ids_that_the_mechanisms_do_not_make_are_refused_by_name(
    roots: tuple[str, str], tmp_path: Path
) -> None:
    """A curated ids file naming a path its shard's mechanisms do not have: the read says which
    file, instead of returning other rows."""
    import shutil

    _, lean = roots
    copy = tmp_path / "lean"
    shutil.copytree(lean, copy)
    store = Store.open(str(copy))
    relative = committed_files(store, "curated")[0]
    table = pq.read_table(copy / relative)
    ids = table.column("path_id").to_numpy().copy()
    ids[0] += 31  # a joint no mechanism of 20 joints or fewer has
    table = table.set_column(0, "path_id", pa.array(ids))
    (copy / relative).unlink()
    pq.write_table(table, copy / relative)
    with pytest.raises(ValueError, match="curated ids are not among its mechanisms' paths"):
        links_ray.load(str(copy), "curated")
    # Without the points, the ids are read as stored.
    assert links_ray.load(str(copy), "curated", columns=["path_id"])["path_id"].iloc[0] == ids[0]


def test_a_writer_refuses_rows_of_another_shape(tmp_path: Path) -> None:
    """A path table is written with all its columns or as ids (all but points): nothing else."""
    store = Store.open(str(tmp_path / "root"))
    bad = SCHEMAS["curated"].remove(SCHEMAS["curated"].get_field_index("is_arc"))
    with ShardWriter(store, 0, 4, stage="curation") as writer:
        with pytest.raises(ValueError, match="rows of curated with columns"):
            writer.write("curated", pa.RecordBatch.from_pylist([], schema=bad))
    assert not list((tmp_path / "root").rglob("*.parquet"))


def test_curate_refuses_an_unknown_store() -> None:
    from links_ray.data.schemas import check_path_store

    with pytest.raises(ValueError, match="store must be one of points, ids, got 'all'"):
        check_path_store("all")


def test_stats_of_a_lean_root_are_those_of_the_stored_one(roots: tuple[str, str]) -> None:
    """Counts and shares of every path made come from the curation markers when no `paths`
    table is stored: the figures of the root that stores it."""
    from links_ray.data.stats import dataset_stats

    stored, lean = (dataset_stats(root) for root in roots)
    assert lean["counts"]["paths"] == stored["counts"]["paths"] and stored["counts"]["paths"]
    assert lean["counts"]["curated"] == stored["counts"]["curated"]
    assert lean["paths_per_mechanism"] == stored["paths_per_mechanism"] > 0
    assert lean["shares"] == stored["shares"]
    assert lean["counts"]["simulations"] is None and stored["counts"]["simulations"]


def test_links_retrieve_and_synthesize_answer_on_a_lean_root_as_on_the_stored_one(
    roots: tuple[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The commands, in this process: the same results (counted work for synthesis)."""
    import json

    from links_ray.cli.main import main

    curated = links_ray.load(roots[0], "curated", columns=["points"], reshape=True)
    drawing = tmp_path / "drawing.json"
    drawing.write_text(json.dumps((curated["points"].iloc[3] * 2.0).tolist()))
    answers = []
    for root in roots:
        for command in (["retrieve", "-k", "4"], ["synthesize", "-k", "2", "--iterations", "2"]):
            assert main([command[0], root, "--points", str(drawing), *command[1:], "--json"]) == 0
            answer = json.loads(capsys.readouterr().out)
            answer.pop("took_ms")
            answers.append(answer)
    stored, lean = answers[:2], answers[2:]
    assert lean == stored and len(stored[0]["results"]) == 4
