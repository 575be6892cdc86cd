"""The retrieval behind the routes is one typed interface (`serve.http.backend`): every backend
implements it with the interface's own signatures (a drifted one fails here), and the
in-process one answers as its index does, pooled as synthesis pools, refusals as 400."""

from __future__ import annotations

import asyncio
import inspect

import numpy as np
import pytest

from links_ray.engine.synthesis.plan import pooled, retrievals
from links_ray.search.index import RetrievalIndex
from links_ray.serve.deployments import PartitionedIndex
from links_ray.serve.http.backend import LocalIndex, RetrievalBackend
from links_ray.serve.http.responses import ApiError
from links_ray.serve.http.routes import LinksApiRoutes
from tests.support.results import assert_same_results


def interface_methods() -> dict[str, inspect.Signature]:
    """The interface's public methods and their signatures."""
    return {
        name: inspect.signature(member, eval_str=True)
        for name, member in vars(RetrievalBackend).items()
        if inspect.isfunction(member) and not name.startswith("_")
    }


@pytest.mark.parametrize("backend", [LocalIndex, PartitionedIndex])
def test_every_backend_keeps_the_interface_signatures(backend: type[RetrievalBackend]) -> None:
    assert issubclass(backend, RetrievalBackend)
    assert not inspect.isabstract(backend)
    for name, signature in interface_methods().items():
        method = getattr(backend, name)
        assert inspect.signature(method, eval_str=True) == signature, f"{backend.__name__}.{name}"


def test_the_signature_check_sees_a_drifted_backend() -> None:
    class Drifted(LocalIndex):
        async def retrieve_waited(  # type: ignore[override]
            self, points: np.ndarray, wanted: int
        ) -> tuple[list[dict], float]:
            return [], 0.0

    drifted = inspect.signature(Drifted.retrieve_waited, eval_str=True)
    assert drifted != interface_methods()["retrieve_waited"]


def test_the_routes_name_the_backend_as_their_only_way_to_the_index() -> None:
    hints = inspect.get_annotations(LinksApiRoutes, eval_str=True)
    assert hints["_backend"] is RetrievalBackend
    assert not [name for name in vars(LinksApiRoutes) if name in ("_retrieve", "_retrieving")]


@pytest.fixture(scope="module")
def local(lean_dataset: str) -> LocalIndex:
    backend = LocalIndex(RetrievalIndex.open(lean_dataset))
    yield backend
    backend.close()


def test_a_local_index_answers_as_its_index_pooled_as_synthesis_pools(
    local: LocalIndex,
) -> None:
    index = local.slot.index
    t = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    points = np.column_stack([0.5 + 0.3 * np.cos(t), 0.5 + 0.2 * np.sin(2 * t)])
    assert_same_results(asyncio.run(local.retrieve(points, 5, 0.0)), index.retrieve(points, 5, 0.0))
    wanted = retrievals(3, None, True, 0.0)  # a front: several retrievals, pooled
    assert len(wanted) > 1
    candidates, waited = asyncio.run(local.retrieve_pooled(points, wanted))
    assert waited >= 0.0
    expected = pooled([index.retrieve(points, count, deg, most) for count, most, deg in wanted])
    assert_same_results(candidates, expected)
    assert asyncio.run(local.health()) == {"paths": len(index)}


def test_a_local_index_refuses_a_query_as_400(local: LocalIndex) -> None:
    flat = np.zeros((10, 2))  # no extent: no curve to match
    with pytest.raises(ApiError) as refused:
        asyncio.run(local.retrieve(flat, 3, 0.0))
    assert refused.value.status == 400 and "no curve" in refused.value.message
