"""The datasets the tests read, generated and curated on the session's Ray cluster.

A pytest plugin (tests/conftest.py lists it): fixtures `dataset` (300 mechanisms), its lean
twin `lean_dataset` (the Serve app's root), `curated`, `reference` (its index), `queries` and
`scale_root` (40,000 curated paths, cached between runs). tests/engine/conftest.py gives the
engine's tests the same dataset made without Ray.
"""

from __future__ import annotations

from typing import Any

import pytest


@pytest.fixture(scope="session")
def dataset(ray_cluster: str, tmp_path_factory: pytest.TempPathFactory) -> str:
    """300 mechanisms, generated and curated, for the Serve app's tests."""
    from links_ray.cluster.curation import curate
    from links_ray.cluster.generation import generate

    out = str(tmp_path_factory.mktemp("serve") / "links")
    generate(out, 300, seed=5, progress=False, topologies_per_shard=10)
    curate(out, progress=False)
    return out


@pytest.fixture(scope="session")
def lean_dataset(tmp_path_factory: pytest.TempPathFactory) -> str:
    """`dataset`'s plan written lean: mechanisms alone and the curated set as ids, the rows of
    `links generate --tables mechanisms` and `links curate --store ids` (made without Ray:
    tests/support/local_dataset.py). The Serve app the HTTP tests talk to serves it, and they
    check its answers against `dataset`'s, which stores every table: HTTP over a lean root
    answers as over a stored one."""
    from links_ray.data.generation import GenerationPlan
    from tests.support.local_dataset import generate_and_curate

    out = str(tmp_path_factory.mktemp("serve-lean") / "links")
    plan = GenerationPlan(seed=5, mechanisms=300, topologies_per_shard=10, tables=("mechanisms",))
    return generate_and_curate(out, plan, curation_tables=("curated",), path_store="ids")


#: Curated paths the large dataset holds at least, and the splits whose every part must
#: still be searched by its coarse lists (more than one list), not only by the sketch scan.
SCALE_PATHS, SCALE_LISTED_SPLITS = 40_000, (1, 2)


@pytest.fixture(scope="session")
def scale_root(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A dataset of at least SCALE_PATHS curated paths (mechanisms and curated only), its index
    saved whole and split in 2 and 4 parts: made once in this process, without Ray, and cached
    between runs (tests/support/scale_data.py), linked into this session's own folder.

    Large enough that the search scans: one index and every part of each split pass on fewer
    candidates than they hold paths (a smaller index estimates every path, in every variant),
    and one index and the parts of 2 hold several coarse lists. Checked here, so that every
    test of it fails if the index's thresholds move above the data."""
    from links_ray.search.index import RetrievalIndex
    from links_ray.search.query import stage_sizes
    from tests.support.scale_data import SPLITS, scale_dataset

    root = tmp_path_factory.mktemp("scale") / "links"
    scale_dataset(root)
    for parts in SPLITS:
        for part in range(parts):
            index = RetrievalIndex.open(str(root), part=part, parts=parts)
            candidates, paths = stage_sizes(len(index))[0], len(index)
            where = f"part {part} of {parts}"
            assert paths >= SCALE_PATHS / parts / 2, f"{where} holds {paths} paths"
            assert candidates < paths, f"{where}: {candidates} candidates of {paths} paths"
            if parts in SCALE_LISTED_SPLITS:
                assert len(index.centroids) > 1, f"{where}: {paths} paths in one coarse list"
            if parts == 1:
                assert paths >= SCALE_PATHS, f"{paths} curated paths"
    return str(root)


@pytest.fixture(scope="session")
def curated(dataset: str) -> Any:
    """The curated paths of `dataset`: path ids and their points (steps, 2)."""
    import links_ray

    return links_ray.load(dataset, "curated", columns=["path_id", "points"], reshape=True)


@pytest.fixture(scope="module")
def queries() -> list:
    """The serving tests' queries: paths of mechanisms held out of the Serve tests' dataset,
    in random frames, and hand-drawn curves."""
    from links_ray.bench.held_out import held_out_queries
    from tests.support.serving import hand_drawn

    return held_out_queries(6, seed=31) + hand_drawn()


@pytest.fixture(scope="module")
def dataset_index(dataset: str) -> Any:
    """One index over every curated path of the Serve tests' dataset."""
    from links_ray.search.index import RetrievalIndex

    return RetrievalIndex.open(dataset)
