"""The Serve deployments, `LinksApi` (the front) and `IndexShard`, and their concurrency limits.

Each front replica opens the retrieval index once, in its constructor. Retrievals run one at a
time per replica (the index's compiled kernels are parallel, and the JIT's workqueue threading
layer, its fallback without TBB or OpenMP, cannot take concurrent callers), in a thread of
their own, so health checks and simulations, in the default thread pool, are answered
meanwhile. A replica holds at most `MAX_RETRIEVALS` retrievals, running or waiting; one more is
answered 503 with `Retry-After` at once, and Serve's own `max_ongoing_requests` and
`max_queued_requests` bound everything else.

Syntheses (`engine.synthesis`) retrieve their candidates as retrievals do (counted against the
same limit), then refine them in a thread of their own at `RETRIEVAL_NICENESS`, one at a time,
for at most their `seconds` counted from when their refinement starts (`queued_ms` says how
long they waited), or for their fixed `iterations`; a replica holds at most `MAX_SYNTHESES`,
running or waiting, answers one more 503 at once, and one that would wait longer than its own
budget 503 too. Each replica's threads are its `num_cpus` (`use_replica_cpus`).

Sharded (`build_app(root, shards=N)`, `links serve --shards N`): N `IndexShard` deployments
each open part P of the index (`RetrievalIndex.open(root, part=P, parts=N)`: the curated shards
numbered P modulo N), and the front, `LinksApi`, holds no index: it asks every part for its own
top k through their deployment handles, at once, and keeps the k best by (chamfer, path id),
the order of one index: no worse than one index's answer, since each part passes on a larger
share of its paths to the exact distance (the same answer where every search is exhaustive;
docs/reference/contract.md). A part that is unavailable, or parts that do not all answer
within `SHARD_TIMEOUT_S`, give 503 with `Retry-After`.

Stopping replicas drain the requests under way for at most `SHUTDOWN_DRAIN_S`. The routes
themselves are `serve.handlers`' `LinksApiRoutes`, which `LinksApi` inherits.
"""

import asyncio
import gc
import math
import os
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import ray
from ray import serve
from ray.exceptions import (
    NodeDiedError,
    ObjectLostError,
    RayActorError,
    RayTaskError,
    TaskCancelledError,
    WorkerCrashedError,
)
from ray.serve.exceptions import (
    BackPressureError,
    DeploymentUnavailableError,
    ReplicaUnavailableError,
)
from ray.serve.handle import DeploymentHandle, DeploymentResponse

from links_ray.engine.cpus import set_given_cpus
from links_ray.engine.solver import simulate
from links_ray.engine.synthesis_plan import pooled
from links_ray.interop.curve_worker import warm_curve_readers
from links_ray.search.index import RetrievalIndex
from links_ray.serve.api import ApiError, allow_host_names, api, logger
from links_ray.serve.handlers import LinksApiRoutes, studio_files

#: Ray starts worker processes at niceness 15, below its own control plane (GCS, raylet,
#: dashboard agent) at 0. A replica answers users, and its parallel kernels wait for their
#: slowest thread, so it runs at 0.
REPLICA_ENV = {"RAY_worker_niceness": "0"}
#: Retrievals are the throughput work; health checks and simulations must be answered at
#: once. So the thread that retrieves, and the kernels' worker threads it starts, run at this
#: niceness (Linux niceness is per thread, and new threads inherit it), below the replica's
#: event loop and thread pool and any front on the same node, still above Ray's workers.
RETRIEVAL_NICENESS = 5
#: Retrievals one front replica holds at once, running or waiting for the index (its own or
#: the shards'). One more is answered at once with 503, `Retry-After` and a JSON `error`: a
#: burst of retrievals neither piles up without bound nor holds what health checks and
#: simulations need.
MAX_RETRIEVALS = 8
#: Syntheses one front replica holds at once, running or waiting. Each holds the replica's
#: cores for its whole budget (up to MAX_SYNTHESIS_SECONDS), so few; one more is answered 503.
#: One that would wait for the refinement thread longer than its own budget is answered 503
#: too: waiting does not shorten its refinement, whose budget starts when it starts.
MAX_SYNTHESES = 2
#: Seconds a refused client is asked to wait (`Retry-After`).
RETRY_AFTER_S = 1
#: Serve's own bounds on a front replica: requests it runs at once, and requests waiting for
#: one of those slots. Beyond them Serve answers 503 with `Retry-After` itself (its body is
#: Serve's plain text, not JSON). Far above MAX_RETRIEVALS, so that health checks and
#: simulations never wait behind retrievals.
FRONT_MAX_ONGOING, FRONT_MAX_QUEUED = 100, 100
#: Retrievals a shard replica takes at once (it runs them one after another); further ones
#: wait in the callers' routers, which send them to the least busy replica of the shard.
SHARD_MAX_ONGOING = 4
#: How long the front waits for all the shards' answers before answering 503.
SHARD_TIMEOUT_S = 30.0
#: Seconds a stopping replica lets the requests under way finish (Serve's
#: `graceful_shutdown_timeout_s`); then it is stopped whatever it holds. Syntheses at their
#: default budget and every other request finish well within it.
SHUTDOWN_DRAIN_S = 20.0
#: How often a draining replica looks whether its requests are done (Serve's
#: `graceful_shutdown_wait_loop_s`, 2 s by default, which an idle replica would wait to stop).
SHUTDOWN_POLL_S = 0.2
#: Shard failures that mean "not there now" (a replica that died or is restarting, a shard
#: with no replica, backpressure): answered 503 with `Retry-After`, not 500.
SHARD_UNAVAILABLE = (
    RayActorError,
    WorkerCrashedError,
    NodeDiedError,
    ObjectLostError,
    TaskCancelledError,  # RequestCancelledError too: a replica stopping under it
    BackPressureError,
    DeploymentUnavailableError,
    ReplicaUnavailableError,
)
#: A four-bar the front simulates once at start, so the solver is loaded before any user asks.
WARM_FOUR_BAR = (
    [[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 1, 0]],
    [0, 2, 0, 1],
    [[0.5, 0.5], [0.55, 0.5], [0.8, 0.5], [0.6, 0.7]],
)
#: The replica's GIL switch interval (seconds; `sys.setswitchinterval`).
GIL_SWITCH_S = 0.0005


def _busy(message: str, retry_after: float = RETRY_AFTER_S) -> ApiError:
    """503 with `Retry-After` (whole seconds, at least RETRY_AFTER_S): come back then."""
    seconds = max(RETRY_AFTER_S, math.ceil(retry_after))
    return ApiError(503, message, headers={"Retry-After": str(seconds)})


def replica_cpus() -> float:
    """The CPUs Ray gave this process (a replica's `num_cpus`, fractions kept; 0 if none)."""
    return float(ray.get_runtime_context().get_assigned_resources().get("CPU", 0.0))


def use_replica_cpus() -> None:
    """Have the engine's and the index's threads keep to the CPUs Ray gave this replica
    (`engine.cpus.usable_cpus`), not the machine's."""
    set_given_cpus(replica_cpus())


class _Turn:
    """A synthesis's place in the line for a replica's refinement thread: its refinement
    budget (None for fixed work, whose length is unknown), when its refinement began, and the
    future set when its turn comes."""

    def __init__(self, budget: float | None) -> None:
        self.budget = budget
        self.began: float | None = None
        self.ready: asyncio.Future[None] = asyncio.get_running_loop().create_future()


def merge_results(answers: list[list[dict]], k: int) -> list[dict]:
    """The k best of several shards' answers (each best first), ordered as one index orders
    them: by chamfer distance, ties to the lower path id."""
    merged = [result for answer in answers for result in answer]
    merged.sort(key=lambda result: (result["chamfer"], result["path_id"]))
    return merged[:k]


class _Retrieving:
    """An index and the one thread its retrievals run in: one at a time (the index's compiled
    kernels are parallel, and the JIT's workqueue threading layer, its fallback without TBB
    or OpenMP, cannot take concurrent callers), never in the thread pool that simulations
    and analyses run in, and at `RETRIEVAL_NICENESS`. The index is warmed in that thread, so
    the kernels' worker threads exist, at that niceness, before the first user asks."""

    def __init__(self, index: RetrievalIndex) -> None:
        self.index = index
        self.pool = ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="links-retrieve", initializer=_lower_priority
        )
        self.pool.submit(index.warm).result()

    async def retrieve(
        self, points: np.ndarray, k: int, min_transmission: float, max_joints: int | None = None
    ) -> list[dict]:
        return await asyncio.get_running_loop().run_in_executor(
            self.pool, self.index.retrieve, points, k, min_transmission, max_joints
        )

    async def retrieve_waited(
        self,
        points: np.ndarray,
        k: int,
        min_transmission: float,
        max_joints: int | None = None,
    ) -> tuple[list[dict], float]:
        """`retrieve`'s answer, and the seconds it waited behind other retrievals."""
        asked = time.perf_counter()
        began: list[float] = []

        def run() -> list[dict]:
            began.append(time.perf_counter())
            return self.index.retrieve(points, k, min_transmission, max_joints)

        results = await asyncio.get_running_loop().run_in_executor(self.pool, run)
        return results, began[0] - asked

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


def _lower_priority() -> None:
    """This thread (and the threads it starts) at RETRIEVAL_NICENESS, if that is lower
    priority than it has; where threads have no niceness of their own, nothing."""
    try:
        thread = threading.get_native_id()
        if os.getpriority(os.PRIO_PROCESS, thread) < RETRIEVAL_NICENESS:
            os.setpriority(os.PRIO_PROCESS, thread, RETRIEVAL_NICENESS)
    except (AttributeError, OSError):  # not Linux
        pass


@serve.deployment(
    name="IndexShard",
    max_ongoing_requests=SHARD_MAX_ONGOING,
    graceful_shutdown_timeout_s=SHUTDOWN_DRAIN_S,
    graceful_shutdown_wait_loop_s=SHUTDOWN_POLL_S,
    ray_actor_options={"num_cpus": 1, "runtime_env": {"env_vars": REPLICA_ENV}},
)
class IndexShard:
    """One part of the retrieval index: the curated shards numbered `part` modulo `parts`.

    Called by the front (`LinksApi`) through its deployment handle, never over HTTP. It opens
    (or builds and saves, under `_links/index/part-P-of-N/`) its part once, warms it, and
    answers each query with its own top k, as a whole index over its paths would.
    """

    def __init__(self, root: str, part: int, parts: int) -> None:
        use_replica_cpus()
        self.part, self.parts = part, parts
        self._retrieving = _Retrieving(RetrievalIndex.open(root, part=part, parts=parts))

    async def info(self) -> dict[str, int]:
        """`{"part", "parts", "paths"}` of this shard."""
        return {"part": self.part, "parts": self.parts, "paths": len(self._retrieving.index)}

    async def retrieve(
        self,
        points: np.ndarray,
        k: int,
        min_transmission: float = 0.0,
        max_joints: int | None = None,
    ) -> list[dict]:
        """The k best results of this part, best first (`RetrievalIndex.retrieve`)."""
        return await self._retrieving.retrieve(points, k, min_transmission, max_joints)

    def __del__(self) -> None:
        if hasattr(self, "_retrieving"):
            self._retrieving.close()


@serve.deployment(
    name="LinksApi",
    max_ongoing_requests=FRONT_MAX_ONGOING,
    max_queued_requests=FRONT_MAX_QUEUED,
    backpressure_config={"status_code": 503, "retry_after_s": RETRY_AFTER_S},
    graceful_shutdown_timeout_s=SHUTDOWN_DRAIN_S,
    graceful_shutdown_wait_loop_s=SHUTDOWN_POLL_S,
    ray_actor_options={"num_cpus": 1, "runtime_env": {"env_vars": REPLICA_ENV}},
)
@serve.ingress(api)
class LinksApi(LinksApiRoutes):
    """The HTTP API of one replica: the retrieval index of `root`, opened once; or, given
    `shards` (deployment handles of `IndexShard` parts 0..N-1, in order), the front that asks
    them all and merges their answers, holding no index itself. It answers requests for its
    addresses, localhost and `allowed_hosts` (`serve.api.HostGuard`)."""

    def __init__(
        self,
        root: str,
        shards: list[DeploymentHandle] | None = None,
        max_retrievals: int = MAX_RETRIEVALS,
        shard_timeout_s: float = SHARD_TIMEOUT_S,
        allowed_hosts: tuple[str, ...] = (),
    ) -> None:
        use_replica_cpus()
        allow_host_names(allowed_hosts)  # for `serve.api.HostGuard`, from the first request on
        self.root = root
        self.shards = list(shards or [])
        self.max_retrievals = max_retrievals
        self.shard_timeout_s = shard_timeout_s
        self._retrievals = 0  # running or waiting; only the event loop's thread counts
        self._shard_paths: list[int] | None = None  # learned from the shards once
        self._retrieving: _Retrieving | None = None
        self._syntheses = 0  # running or waiting; only the event loop's thread counts
        self._line: list[_Turn] = []  # for the refinement thread: the first holds it
        # Refinement runs here, one synthesis at a time (each uses every core itself), at the
        # retrievals' niceness, never in the thread pool health checks and simulations use.
        self._refining = ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="links-synthesize", initializer=_lower_priority
        )
        if self.shards:
            simulate(*WARM_FOUR_BAR, steps=8)  # loads the solver /api/simulate uses
        else:  # warming the index also loads the solver /api/simulate uses
            self._retrieving = _Retrieving(RetrievalIndex.open(root))
        studio_files()  # a package without the studio fails here, not on a user's first visit
        warm_curve_readers()  # the processes /api/curve reads drawings in
        # What the replica holds from here on (the index, the compiled kernels, the libraries'
        # objects) is not garbage: out of the collector's sight, a full collection (which the
        # objects of large bodies and answers set off) walks only what requests made, not
        # the libraries' whole heap, holding the GIL all the while.
        gc.collect()
        gc.freeze()
        # A thread that wants the GIL (the event loop's, to answer a health check) waits this
        # long before the holder must yield it: 5 ms by default, paid at every hop of a request
        # while JSON is parsed or rendered in JSON_POOL.
        sys.setswitchinterval(GIL_SWITCH_S)

    def __del__(self) -> None:
        if getattr(self, "_retrieving", None) is not None:
            self._retrieving.close()
        if hasattr(self, "_refining"):
            self._refining.shutdown(wait=False, cancel_futures=True)

    async def _retrieve(
        self, points: np.ndarray, k: int, floor: float, max_joints: int | None = None
    ) -> list[dict]:
        """The k best results for a query: from this replica's index (a ValueError it raises
        answered 400), or the shards' answers merged."""
        if self._retrieving is not None:
            try:
                return await self._retrieving.retrieve(points, k, floor, max_joints)
            except ValueError as exc:
                raise ApiError(400, str(exc)) from None
        answers = await self._ask_shards("retrieve", points, k, floor, max_joints)
        return merge_results(answers, k)

    async def _synthesis_candidates(
        self, points: np.ndarray, wanted: list[tuple[int, int | None]], floor: float
    ) -> tuple[list[dict], float]:
        """A synthesis's retrieved candidates (`synthesis.retrievals`: (count, max_joints)
        each, `pooled`), counted against the retrieval limit as one retrieval (503 beyond
        it), and the seconds they waited behind other retrievals (0 with shards: they wait in
        the shards' replicas)."""
        self._claim_retrieval()
        try:
            answers, waited = [], 0.0
            for count, most in wanted:
                if self._retrieving is not None:
                    answer, wait = await self._retrieving.retrieve_waited(
                        points, count, floor, most
                    )
                    answers.append(answer)
                    waited += wait
                else:
                    shards = await self._ask_shards("retrieve", points, count, floor, most)
                    answers.append(merge_results(shards, count))
            return pooled(answers), waited
        finally:
            self._retrievals -= 1

    def _claim_retrieval(self) -> None:
        """Count one more retrieval under way, or refuse it 503 at the limit."""
        if self._retrievals >= self.max_retrievals:
            raise _busy(
                f"busy: {self._retrievals} retrievals under way, the most this server "
                f"holds; retry after {RETRY_AFTER_S} s"
            )
        self._retrievals += 1

    def _claim_synthesis(self) -> None:
        """Count one more synthesis under way, or refuse it 503 at MAX_SYNTHESES."""
        if self._syntheses >= MAX_SYNTHESES:
            raise _busy(
                f"busy: {self._syntheses} syntheses under way, the most this server holds; "
                f"retry after {RETRY_AFTER_S} s"
            )
        self._syntheses += 1

    def _expected_wait(self) -> float | None:
        """Seconds until the syntheses in line end their budgets; None if one does fixed work
        (its length is not known beforehand)."""
        now = time.perf_counter()
        wait = 0.0
        for turn in self._line:
            if turn.budget is None:
                return None
            wait += turn.budget if turn.began is None else max(0.0, turn.began + turn.budget - now)
        return wait

    async def _wait_for_refiner(self, budget: float | None, patience: float) -> _Turn:
        """This synthesis's turn at the refinement thread, once the ones before it are done;
        503 with `Retry-After` if it would wait longer than `patience` seconds: at once when
        the wait is known beforehand, else once it has waited that long."""
        expected = self._expected_wait()
        if expected is not None and expected > patience:
            raise _busy(
                f"busy: the syntheses under way end in about {expected:.1f} s, longer than "
                f"this one may wait ({max(0.0, patience):.1f} s of its budget)",
                retry_after=expected - max(0.0, patience),
            )
        turn = _Turn(budget)
        self._line.append(turn)
        if len(self._line) == 1:
            turn.ready.set_result(None)
        try:
            await asyncio.wait({turn.ready}, timeout=max(0.0, patience))
        except BaseException:  # the client went away: its place, or its turn, goes on
            self._next_turn(turn)
            raise
        if not turn.ready.done():
            self._next_turn(turn)
            raise _busy(
                f"busy: waited {max(0.0, patience):.1f} s for the syntheses under way, as "
                "long as this one may wait; retry after they end"
            )
        return turn

    def _next_turn(self, turn: _Turn) -> None:
        """`turn` is done with the refinement thread: the next in line takes it."""
        self._line.remove(turn)
        if self._line and not self._line[0].ready.done():
            self._line[0].ready.set_result(None)

    def _synthesis_done(self, turn: _Turn, _: object = None) -> None:
        self._syntheses -= 1
        self._next_turn(turn)

    async def _shard_counts(self) -> list[int]:
        """Each shard's paths, asked once (a shard's index does not change while it serves)."""
        if self._shard_paths is None:
            infos = await self._ask_shards("info")
            self._shard_paths = [info["paths"] for info in infos]
        return self._shard_paths

    async def _ask_shards(self, method: str, *args: Any) -> list[Any]:
        """Every shard's answer to `method(*args)`, in part order, asked at once; ApiError
        503 if one is unavailable or they do not all answer within `shard_timeout_s`."""
        tasks = [
            asyncio.ensure_future(self._ask_shard(part, getattr(shard, method).remote(*args)))
            for part, shard in enumerate(self.shards)
        ]
        try:
            return await asyncio.wait_for(asyncio.gather(*tasks), self.shard_timeout_s)
        except TimeoutError:
            raise _busy(
                f"the index shards did not answer within {self.shard_timeout_s:g} s"
            ) from None
        finally:
            for task in tasks:  # after a failure, stop asking the others
                task.cancel()

    async def _ask_shard(self, part: int, response: DeploymentResponse) -> Any:
        """One shard's answer; its failures as ApiErrors: 503 for a shard that is not there
        now, 400 for a query it refuses, else 500 (logged by type, never the request)."""
        try:
            return await response
        except asyncio.CancelledError:  # another part failed, or time ran out: stop this one
            response.cancel()
            raise
        except SHARD_UNAVAILABLE as exc:
            logger.warning(
                "links-ray API: shard %d of %d unavailable (%s)",
                part,
                len(self.shards),
                type(exc).__name__,
            )
            raise _busy(f"index shard {part} of {len(self.shards)} is unavailable") from None
        except RayTaskError as exc:  # the shard's own exception
            if isinstance(exc.cause, ValueError):
                raise ApiError(400, str(exc.cause)) from None
            logger.error(
                "links-ray API: shard %d of %d failed with %s",
                part,
                len(self.shards),
                type(exc.cause).__name__,
            )
            raise ApiError(500, "internal error") from None
