"""The engine's tests read a dataset made without Ray (tests/support/local_dataset.py): the
same plan and seeds as the session's `dataset` (tests/support/datasets.py), so the same rows,
generated and curated in this process. tests/run runs this folder with Ray blocked
(`-p tests.support.no_ray`).

`curated` and `dataset_index` are defined again here, over this `dataset`, so that a run of the
whole tree in one process never hands the engine's tests the value cached for the other one.
"""

from __future__ import annotations

from typing import Any

import pytest


@pytest.fixture(scope="session")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> str:
    """300 mechanisms, generated and curated in this process (seed 5, 10 topologies a shard)."""
    from links_ray.data.generation import GenerationPlan
    from tests.support.local_dataset import generate_and_curate

    out = str(tmp_path_factory.mktemp("engine") / "links")
    return generate_and_curate(out, GenerationPlan(seed=5, mechanisms=300, topologies_per_shard=10))


@pytest.fixture(scope="session")
def curated(dataset: str) -> Any:
    """The curated paths of `dataset`: path ids and their points (steps, 2)."""
    import links_ray

    return links_ray.load(dataset, "curated", columns=["path_id", "points"], reshape=True)


@pytest.fixture(scope="session")
def dataset_index(dataset: str) -> Any:
    """One index over every curated path of `dataset`, built without Ray."""
    from links_ray.search.index import RetrievalIndex

    return RetrievalIndex.open(dataset)
