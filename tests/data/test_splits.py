"""Train / validation / test splits by topology: their shares, their stability as a dataset
is extended, and `load` and `ray_dataset` with `split=` against the split of every row's topology,
found by joining on the `mechanisms` table (not by the id arithmetic the split uses)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.dataset as pads
import pytest

import links_ray
from links_ray.data.generation import GenerationPlan, mechanism_topology, write_shard
from links_ray.data.schemas import TABLE_NAMES
from links_ray.data.store import Store

GENERATION = ("mechanisms", "simulations", "negatives")
#: Each table's row id.
ROW_ID = {
    "mechanisms": "mechanism_id",
    "simulations": "mechanism_id",
    "negatives": "mechanism_id",
    "paths": "path_id",
    "curated": "path_id",
}


def _generated(root: Path, mechanisms: int) -> str:
    """A root generated without Ray: seed 9, two topologies a shard."""
    store = Store.open(str(root))
    plan = GenerationPlan(seed=9, mechanisms=mechanisms, topologies_per_shard=2)
    for shard in plan.shards():
        write_shard(store, plan, shard)
    return str(root)


@pytest.fixture(scope="module")
def extended(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    """The same plan at 40 and at 80 mechanisms (8 and 16 topologies)."""
    folder = tmp_path_factory.mktemp("splits")
    return _generated(folder / "small", 40), _generated(folder / "large", 80)


def _topologies(root: str, table: str, rows: pd.DataFrame) -> np.ndarray:
    """Each row's topology: its own column, else its mechanism's row in `mechanisms`."""
    if "topology_id" in rows:
        return rows["topology_id"].to_numpy()
    owners = links_ray.load(root, "mechanisms", columns=["mechanism_id", "topology_id"])
    owner = dict(zip(owners["mechanism_id"], owners["topology_id"], strict=True))
    return np.array([owner[m] for m in rows["mechanism_id"]], dtype=np.int64)


def test_shares_are_close_to_the_fractions() -> None:
    ids = np.arange(300_000, dtype=np.int64)
    for fractions in (None, (0.5, 0.25, 0.25), (0.7, 0.0, 0.3)):
        splits = links_ray.split_of(ids, fractions)
        for name, share in zip(links_ray.SPLITS, fractions or (0.8, 0.1, 0.1), strict=True):
            # Six standard deviations of a binomial share: fails with odds below 1e-8.
            bound = 6 * math.sqrt(share * (1 - share) / len(ids))
            assert abs(np.mean(splits == name) - share) <= bound, (fractions, name)


def test_a_split_is_a_function_of_the_id_alone() -> None:
    """The same id gets the same split in any company: alone, shuffled, among more ids."""
    rng = np.random.default_rng(1)
    ids = rng.integers(0, 2**40, size=2000)
    splits = links_ray.split_of(ids)
    assert [links_ray.split_of([i])[0] for i in ids[:50]] == list(splits[:50])
    order = rng.permutation(len(ids))
    assert np.array_equal(links_ray.split_of(ids[order]), splits[order])
    more = np.concatenate([rng.integers(0, 2**40, size=5000), ids])
    assert np.array_equal(links_ray.split_of(more)[5000:], splits)


def test_a_larger_fraction_takes_ids_only_from_its_neighbour() -> None:
    ids = np.arange(50_000)
    before = links_ray.split_of(ids, (0.8, 0.1, 0.1))
    after = links_ray.split_of(ids, (0.7, 0.2, 0.1))
    moved = before != after
    assert moved.any()
    assert set(before[moved]) == {"train"} and set(after[moved]) == {"validation"}
    assert np.array_equal(before == "test", after == "test")


@pytest.mark.parametrize(
    ("fractions", "message"),
    [
        ((0.8, 0.1), "three non-negative numbers"),
        ((0.8, 0.3, -0.1), "three non-negative numbers"),
        ((0.8, 0.1, 0.05), "must sum to 1"),
        ("abc", "must be three numbers"),
    ],
)
def test_bad_fractions_are_value_errors(fractions: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        links_ray.split_of([1, 2, 3], fractions)


def test_bad_ids_and_split_names_are_value_errors(extended: tuple[str, str]) -> None:
    with pytest.raises(ValueError, match="must be integers"):
        links_ray.split_of([0.5])
    with pytest.raises(ValueError, match="non-negative"):
        links_ray.split_of([-1])
    with pytest.raises(ValueError, match="split must be one of train, validation, test"):
        links_ray.load(extended[0], "mechanisms", split="dev")
    with pytest.raises(ValueError, match="must sum to 1"):
        links_ray.load(extended[0], "mechanisms", split="test", split_fractions=(0.5, 0.1, 0.1))


def test_mechanism_ids_give_their_topology(extended: tuple[str, str]) -> None:
    """The id arithmetic the split relies on, against the stored topology ids, negatives too."""
    for table in ("mechanisms", "negatives"):
        rows = links_ray.load(extended[1], table, columns=["mechanism_id", "topology_id"])
        assert len(rows)
        topologies = mechanism_topology(rows["mechanism_id"].to_numpy())
        assert np.array_equal(topologies, rows["topology_id"].to_numpy())


def test_rows_keep_their_split_as_the_dataset_is_extended(extended: tuple[str, str]) -> None:
    """Generated again at twice the size with the same seed, each table's rows of one split
    are a subset of the larger dataset's rows of that split, the same rows; and every row is
    in the split of its topology."""
    small, large = extended
    for table in GENERATION:
        key = ROW_ID[table]
        everything = links_ray.load(small, table)
        parts = {s: links_ray.load(small, table, split=s) for s in links_ray.SPLITS}
        ids = np.concatenate([p[key].to_numpy() for p in parts.values()])
        assert sorted(ids) == sorted(everything[key]), table  # a partition of the rows
        for split, rows in parts.items():
            assert (links_ray.split_of(_topologies(small, table, rows)) == split).all()
            extended_rows = links_ray.load(large, table, split=split).set_index(key)
            assert set(rows[key]) <= set(extended_rows.index), (table, split)
            assert len(extended_rows) >= len(rows)
            for row in rows.itertuples():
                other = extended_rows.loc[getattr(row, key)]
                column = "trajectories" if table == "simulations" else "positions"
                assert np.array_equal(getattr(row, column), other[column])
    counts = [len(links_ray.load(large, "mechanisms", split=s)) for s in links_ray.SPLITS]
    assert sum(counts) == 80


@pytest.mark.parametrize("table", TABLE_NAMES)
def test_load_keeps_exactly_the_rows_of_the_split(dataset: str, table: str) -> None:
    """Every table's rows of one topology land in one split: its topology's."""
    key = ROW_ID[table]
    owner = "topology_id" if table in ("mechanisms", "negatives") else "mechanism_id"
    everything = links_ray.load(dataset, table, columns=list(dict.fromkeys([key, owner])))
    truth = links_ray.split_of(_topologies(dataset, table, everything))
    for split in links_ray.SPLITS:
        rows = links_ray.load(dataset, table, columns=[key], split=split)
        assert list(rows.columns) == [key]
        assert sorted(rows[key]) == sorted(everything[key][truth == split]), (table, split)
    assert {"train", "validation", "test"} == set(truth)


def test_ray_dataset_keeps_exactly_the_rows_of_the_split(dataset: str) -> None:
    """With a joint-count filter, a column filter and columns that leave out the split's key."""
    counts = sorted(set(links_ray.load(dataset, "curated", columns=["n_joints"])["n_joints"]))
    wanted = counts[:3]
    floor = 5.0
    for split in ("train", "validation"):
        rows = links_ray.ray_dataset(
            dataset,
            "curated",
            n_joints=wanted,
            columns=["path_id", "points", "min_transmission_deg"],
            filter=pads.field("min_transmission_deg") >= floor,
            split=split,
        ).to_pandas()
        plain = links_ray.ray_dataset(
            dataset, "curated", columns=["path_id", "points", "min_transmission_deg"]
        )
        assert sorted(rows.columns) == sorted(plain.schema().names)
        expected = links_ray.load(dataset, "curated", n_joints=wanted, split=split)
        expected = expected[expected["min_transmission_deg"] >= floor]
        assert 0 < len(rows) == len(expected)
        assert sorted(rows["path_id"]) == sorted(expected["path_id"])
    mechanisms = links_ray.ray_dataset(dataset, "mechanisms", split="test").to_pandas()
    truth = links_ray.load(dataset, "mechanisms", split="test")
    assert sorted(mechanisms["mechanism_id"]) == sorted(truth["mechanism_id"])
    with pytest.raises(ValueError, match="split must be one of"):
        links_ray.ray_dataset(dataset, "mechanisms", split="dev")
