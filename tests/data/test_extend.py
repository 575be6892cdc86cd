"""A root is extended in place: the same seed's plan extended, earlier shards kept bit for bit, the
extended root's rows those of a fresh run of the larger size, and extending deterministic. Shards
are written as a generator actor writes them (`data.generation.write_shard`), without Ray;
tests/cluster/test_generation.py extends a root through `links generate` itself."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pyarrow as pa
import pytest

import links_ray
from links_ray.data.commit import committed_shards
from links_ray.data.generation import GenerationPlan
from links_ray.data.schemas import GENERATION_TABLES
from links_ray.data.store import Store
from tests.support.local_dataset import generate_and_curate

#: 137 and 263 split topologies 27 and 52 between sizes (5 variants a topology).
FIRST, EXTENDED = 137, 263
PLAN = GenerationPlan(seed=5, mechanisms=FIRST, topologies_per_shard=3)
SORT_KEY = {
    "mechanisms": "mechanism_id",
    "simulations": "mechanism_id",
    "negatives": "mechanism_id",
    "curated": "path_id",
}


def write_missing(root: str, plan: GenerationPlan) -> None:
    """Write and curate the shards of `plan` that `root` does not hold yet, as a resumed
    `links generate` and `links curate` would."""
    generate_and_curate(root, plan, curation_tables=("curated",))


def rows(root: str, table: str) -> pa.Table:
    return links_ray.load(root, table, format="arrow").sort_by(SORT_KEY[table])


def file_digests(root: str) -> dict[str, str]:
    return {
        str(path.relative_to(root)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in Path(root).rglob("*.parquet")
    }


@pytest.fixture(scope="module")
def roots(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """A root of FIRST mechanisms, its copy extended to EXTENDED, and a fresh root of EXTENDED."""
    folder = tmp_path_factory.mktemp("extension")
    first, extended, fresh = (str(folder / name) for name in ("first", "extended", "fresh"))
    write_missing(first, PLAN)
    shutil.copytree(first, extended)
    write_missing(extended, PLAN.extended_to(EXTENDED))
    write_missing(fresh, GenerationPlan(seed=5, mechanisms=EXTENDED, topologies_per_shard=3))
    return {"first": first, "extended": extended, "fresh": fresh}


def test_an_extended_root_keeps_every_earlier_file_bit_for_bit(roots: dict[str, str]) -> None:
    before, after = file_digests(roots["first"]), file_digests(roots["extended"])
    assert before and {name: after.get(name) for name in before} == before
    assert len(after) > len(before)


@pytest.mark.parametrize("table", [*GENERATION_TABLES, "curated"])
def test_an_extended_root_holds_the_rows_of_a_fresh_run_of_its_size(
    roots: dict[str, str], table: str
) -> None:
    extended, fresh = rows(roots["extended"], table), rows(roots["fresh"], table)
    assert len(fresh) > 0 and extended.equals(fresh)
    if table == "mechanisms":
        assert extended["mechanism_id"].to_pylist() == list(range(EXTENDED))


def test_a_split_topology_is_counted_once(roots: dict[str, str]) -> None:
    def totals(root: str) -> dict[str, int]:
        markers = committed_shards(Store.open(root, writable=False), "shards").values()
        keys = ("topologies", "mechanisms", "candidates", "valid", "negatives", "abandoned")
        return {key: sum(m["stats"][key] for m in markers) for key in keys}

    assert totals(roots["extended"]) == totals(roots["fresh"])


def test_extending_twice_from_copies_gives_the_same_shards(
    roots: dict[str, str], tmp_path: Path
) -> None:
    again, twice = str(tmp_path / "again"), str(tmp_path / "twice")
    for root in (again, twice):
        shutil.copytree(roots["first"], root)
        write_missing(root, PLAN.extended_to(200))
        write_missing(root, PLAN.extended_to(200).extended_to(EXTENDED))
    for table in [*GENERATION_TABLES, "curated"]:
        assert rows(again, table).equals(rows(twice, table)), table
    shards = [
        committed_shards(Store.open(root, writable=False), "shards") for root in (again, twice)
    ]
    assert {k: m["rows"] for k, m in shards[0].items()} == {
        k: m["rows"] for k, m in shards[1].items()
    }
    # Two extensions make the rows of one: their order changes shards, not rows.
    assert rows(again, "mechanisms").equals(rows(roots["fresh"], "mechanisms"))


def test_a_plan_is_extended_but_never_shrinks() -> None:
    extended = PLAN.extended_to(EXTENDED)
    assert extended.extended_from == (FIRST,) and extended.mechanisms == EXTENDED
    assert PLAN.extended_to(FIRST) is PLAN
    # The root's shards are the extended plan's first ones, as they were: none is redone.
    assert extended.shards()[: len(PLAN.shards())] == PLAN.shards()
    with pytest.raises(
        ValueError, match="holds 137 mechanisms: a root is extended, it never shrinks"
    ):
        PLAN.extended_to(100)
    with pytest.raises(ValueError, match="extended_from must hold at most 1,000 sizes, got 5,000"):
        GenerationPlan(seed=5, mechanisms=10**6, extended_from=list(range(1, 5001)))
    for sizes in ([137, 100], [0], [300], "137", [True]):
        with pytest.raises(ValueError, match="extended_from must"):
            GenerationPlan(seed=5, mechanisms=263, extended_from=sizes)
