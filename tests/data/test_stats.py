"""`links stats` without reading what it need not: counts from the commit markers equal to
the rows a plain read finds, shares counted batch by batch equal to whole-table counts, and
the transmission quantiles those of numpy on the whole column. Made without Ray."""

from __future__ import annotations

import json
import shutil
from collections import Counter

import numpy as np
import pyarrow.dataset as pads
import pytest

from links_ray.data.generation import GenerationPlan
from links_ray.data.schemas import TABLE_NAMES
from links_ray.data.stats import TRANSMISSION_QUANTILES, dataset_stats
from tests.support.local_dataset import generate_and_curate


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> str:
    folder = tmp_path_factory.mktemp("stats")
    return generate_and_curate(str(folder / "root"), GenerationPlan(seed=4, mechanisms=263))


def test_stats_are_those_of_the_rows(root: str) -> None:
    stats = dataset_stats(root, sample_topologies=1)
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
        dataset_stats(str(lying), sample_topologies=1)
