"""The engine's tests read a dataset made without Ray (tests/support/local_dataset.py, used by
tests/engine/conftest.py): the same plan on Ray, `generate` then `curate` (the session's
`dataset`), gives the same rows in every table."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa

import links_ray
from links_ray.data.generation import GenerationPlan
from tests.support.local_dataset import generate_and_curate

TABLES = ("mechanisms", "simulations", "negatives", "paths", "curated")


def rows(root: str, table: str) -> pa.Table:
    loaded = links_ray.load(root, table, format="arrow")
    key = "path_id" if "path_id" in loaded.column_names else "mechanism_id"
    loaded = loaded.select(sorted(loaded.column_names))
    return loaded.sort_by(key).combine_chunks()


def test_the_engine_tests_dataset_has_the_rows_ray_makes(dataset: str, tmp_path: Path) -> None:
    plan = GenerationPlan(seed=5, mechanisms=300, topologies_per_shard=10)  # as `dataset`
    local = generate_and_curate(str(tmp_path / "links"), plan)
    for table in TABLES:
        on_ray, here = rows(dataset, table), rows(local, table)
        assert len(on_ray) > 0, table
        assert on_ray.equals(here), table
