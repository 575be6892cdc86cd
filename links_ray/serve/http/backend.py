"""The retrieval behind the routes (`RetrievalBackend`): what `/api/retrieve`,
`/api/synthesize` and `/api/health` ask of an index, as one typed interface. `LocalIndex` is
one index in this process, searched in a thread of its own (`RetrievalSlot`); the Serve
deployments provide the other, an index split into partitions (`serve.deployments`).

Nothing here imports Ray.
"""

from __future__ import annotations

import asyncio
import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from links_ray.engine.synthesis.plan import RetrievalResult, pooled
from links_ray.serve.http.admission import low_priority_thread
from links_ray.serve.http.responses import ApiError

if TYPE_CHECKING:  # only a type here: the routes, and the docs, need no index module
    from links_ray.search.index import RetrievalIndex

#: One of a synthesis's retrievals (`engine.synthesis.plan.retrievals`): how many paths, of at
#: most how many joints (None: any), with at least which transmission angle in degrees.
Retrieval = tuple[int, int | None, float]


class RetrievalBackend(ABC):
    """An index the routes retrieve from. Answers are lists of result dicts, best first, as
    `RetrievalIndex.retrieve` gives them (numpy arrays in them: the routes' JSON rendering makes
    them lists); a query the index refuses is ApiError 400, an index that cannot answer now
    ApiError 503."""

    @abstractmethod
    async def retrieve_waited(
        self,
        points: np.ndarray,
        k: int,
        min_transmission_deg: float,
        max_joints: int | None = None,
    ) -> tuple[list[RetrievalResult], float]:
        """The k best results for a query, and the seconds it waited behind other retrievals
        before its own began."""

    @abstractmethod
    async def health(self) -> dict[str, Any]:
        """What `/api/health` says of the index beside `"status"`: its `paths`, and for a
        partitioned one each partition's (`shards`)."""

    def close(self) -> None:
        """Let go of what the backend holds (threads, handles); nothing by default."""
        return None

    async def retrieve(
        self,
        points: np.ndarray,
        k: int,
        min_transmission_deg: float,
        max_joints: int | None = None,
    ) -> list[RetrievalResult]:
        """The k best results for a query, best first."""
        results, _ = await self.retrieve_waited(points, k, min_transmission_deg, max_joints)
        return results

    async def retrieve_pooled(
        self, points: np.ndarray, wanted: Sequence[Retrieval]
    ) -> tuple[list[RetrievalResult], float]:
        """A synthesis's candidates: each retrieval of `wanted` in turn, pooled
        (`engine.synthesis.plan.pooled`), and the seconds they waited in all."""
        answers, waited = [], 0.0
        for count, most, min_transmission_deg in wanted:
            answer, wait = await self.retrieve_waited(points, count, min_transmission_deg, most)
            answers.append(answer)
            waited += wait
        return pooled(answers), waited


class RetrievalSlot:
    """An index and the one thread its retrievals run in: one at a time (the index's compiled
    kernels are parallel, and the JIT's workqueue threading layer, its fallback without TBB
    or OpenMP, cannot take concurrent callers), never in the thread pool that simulations
    and analyses run in, and at `admission.RETRIEVAL_NICENESS`. The index is warmed in that
    thread, so the kernels' worker threads exist, at that niceness, before the first user
    asks."""

    def __init__(self, index: RetrievalIndex) -> None:
        self.index = index
        self.pool = low_priority_thread("links-retrieve")
        self.pool.submit(index.warm).result()

    async def retrieve_waited(
        self,
        points: np.ndarray,
        k: int,
        min_transmission_deg: float,
        max_joints: int | None = None,
    ) -> tuple[list[RetrievalResult], float]:
        """`RetrievalIndex.retrieve`'s answer, from the slot's thread, and the seconds it
        waited behind other retrievals."""
        asked = time.perf_counter()
        began: list[float] = []

        def run() -> list[RetrievalResult]:
            began.append(time.perf_counter())
            return self.index.retrieve(points, k, min_transmission_deg, max_joints)

        results = await asyncio.get_running_loop().run_in_executor(self.pool, run)
        return results, began[0] - asked

    def close(self) -> None:
        """Stop the thread, dropping retrievals not yet begun."""
        self.pool.shutdown(wait=False, cancel_futures=True)


class LocalIndex(RetrievalBackend):
    """One index in this process (`RetrievalSlot`): a query it refuses is ApiError 400."""

    def __init__(self, index: RetrievalIndex) -> None:
        self.slot = RetrievalSlot(index)

    async def retrieve_waited(
        self,
        points: np.ndarray,
        k: int,
        min_transmission_deg: float,
        max_joints: int | None = None,
    ) -> tuple[list[RetrievalResult], float]:
        """The slot's answer; its ValueError as ApiError 400."""
        try:
            return await self.slot.retrieve_waited(points, k, min_transmission_deg, max_joints)
        except ValueError as exc:
            raise ApiError(400, str(exc)) from None

    async def health(self) -> dict[str, Any]:
        """The index's paths."""
        return {"paths": len(self.slot.index)}

    def close(self) -> None:
        """Stop the slot's thread."""
        self.slot.close()
