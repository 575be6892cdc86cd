"""The Serve deployments, `LinksApi` (the gateway) and `IndexPartition`, and their limits.

Each gateway replica opens the retrieval index once, in its constructor, and answers HTTP with the
app of `serve.http.asgi`. Its admission (`serve.http.admission`) bounds the retrievals and syntheses
it holds: one more is answered 503 with `Retry-After` at once, and Serve's own
`max_ongoing_requests` and `max_queued_requests` bound everything else. Retrievals run one at a time
in a thread beside the index, syntheses refine one at a time in a thread of their own, so health
checks and simulations, in the default thread pool, are answered meanwhile. Each replica's threads
are its `num_cpus` (`use_replica_cpus`).

With the index split into N partitions (`build_app(root, shards=N)`, `links serve --shards N`):
N `IndexPartition` deployments each open part P of the index (`RetrievalIndex.open(root,
part=P, parts=N)`: the curated shards numbered P modulo N), and the gateway, `LinksApi`, holds
no index: it asks every partition for its own top k through their deployment handles, at
once, and keeps the k best by (chamfer, path id), the order of one index: no worse than one
index's answer, since each partition passes on a larger share of its paths to the exact
distance (the same answer where every search is exhaustive; docs/reference/contract.md). A
partition that is unavailable, or partitions that do not all answer within
`PARTITION_TIMEOUT_S`, give 503 with `Retry-After`.

Stopping replicas drain the requests under way for at most `SHUTDOWN_DRAIN_S`. The routes
themselves are `serve.http.routes`' `LinksApiRoutes`, which `LinksApi` inherits, giving them
their retrieval backend: `serve.http.backend.LocalIndex`, or `PartitionedIndex` here.
"""

import asyncio
import gc
import sys
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
from links_ray.engine.kinematics.solver import simulate
from links_ray.engine.synthesis.plan import RetrievalResult
from links_ray.engine.synthesis.warm import warm_default
from links_ray.interop.curve_worker import warm_curve_readers
from links_ray.search.index import RetrievalIndex
from links_ray.serve.http.admission import Admission, busy, low_priority_thread
from links_ray.serve.http.asgi import api
from links_ray.serve.http.backend import LocalIndex, RetrievalBackend, RetrievalSlot
from links_ray.serve.http.limits import (
    GATEWAY_MAX_ONGOING,
    GATEWAY_MAX_QUEUED,
    MAX_RETRIEVALS,
    PARTITION_MAX_ONGOING,
    PARTITION_TIMEOUT_S,
    RETRY_AFTER_S,
)
from links_ray.serve.http.middleware import allow_host_names
from links_ray.serve.http.responses import ApiError, logger
from links_ray.serve.http.routes import LinksApiRoutes, studio_files

#: Ray starts worker processes at niceness 15, below its own control plane (GCS, raylet,
#: dashboard agent) at 0. A replica answers users, and its parallel kernels wait for their
#: slowest thread, so it runs at 0.
REPLICA_ENV = {"RAY_worker_niceness": "0"}
#: Seconds a stopping replica lets the requests under way finish (Serve's
#: `graceful_shutdown_timeout_s`); then it is stopped whatever it holds. Syntheses at their
#: default budget and every other request finish well within it.
SHUTDOWN_DRAIN_S = 20.0
#: How often a draining replica looks whether its requests are done (Serve's
#: `graceful_shutdown_wait_loop_s`, 2 s by default, which an idle replica would wait to stop).
SHUTDOWN_POLL_S = 0.2
#: Partition failures that mean "not there now" (a replica that died or is restarting, a
#: partition with no replica, backpressure): answered 503 with `Retry-After`, not 500.
PARTITION_UNAVAILABLE = (
    RayActorError,
    WorkerCrashedError,
    NodeDiedError,
    ObjectLostError,
    TaskCancelledError,  # RequestCancelledError too: a replica stopping under it
    BackPressureError,
    DeploymentUnavailableError,
    ReplicaUnavailableError,
)
#: A four-bar the gateway simulates once at start, so the solver is loaded before any user asks.
WARM_FOUR_BAR = (
    [[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 1, 0]],
    [0, 2, 0, 1],
    [[0.5, 0.5], [0.55, 0.5], [0.8, 0.5], [0.6, 0.7]],
)
#: The replica's GIL switch interval (seconds; `sys.setswitchinterval`).
GIL_SWITCH_S = 0.0005


def keep_replica_grpc_on_loopback() -> None:
    """On a Ray whose node address is loopback (what `links serve --host 127.0.0.1` starts),
    have this replica's inter-deployment gRPC server listen on 127.0.0.1 too.

    Ray 2.60's replica binds that server to every interface (`[::]:0`), with no option to
    change it, once its constructor has returned; on a loopback node nothing but this machine
    could reach it anyway, so it is bound where the node is. The helper Ray calls is looked up
    in its module at that moment, so replacing it there suffices; if a Ray upgrade renames it,
    this does nothing, and tests/serve/test_serve_sockets.py, which lists every listening
    socket of `links serve`, says so.
    """
    import ipaddress

    try:
        if not ipaddress.ip_address(ray.util.get_node_ip_address()).is_loopback:
            return
        from ray.serve._private import replica
    except (ValueError, ImportError):
        return
    bind = getattr(replica, "add_port_to_grpc_server", None)
    if bind is None or getattr(bind, "links_on_loopback", False):
        return

    def bind_on_loopback(server: Any, address: str) -> int:
        if address.startswith("[::]:"):
            address = "127.0.0.1:" + address.rsplit(":", 1)[1]
        return bind(server, address)

    bind_on_loopback.links_on_loopback = True  # type: ignore[attr-defined]
    replica.add_port_to_grpc_server = bind_on_loopback


def replica_cpus() -> float:
    """The CPUs Ray gave this process (a replica's `num_cpus`, fractions kept; 0 if none)."""
    return float(ray.get_runtime_context().get_assigned_resources().get("CPU", 0.0))


def use_replica_cpus() -> None:
    """Have the engine's and the index's threads keep to the CPUs Ray gave this replica
    (`engine.cpus.usable_cpus`), not the machine's."""
    set_given_cpus(replica_cpus())


def merge_results(answers: list[list[RetrievalResult]], k: int) -> list[RetrievalResult]:
    """The k best of several partitions' answers (each best first), ordered as one index orders
    them: by chamfer distance, ties to the lower path id. The results are kept as they came,
    their arrays too (they cross the deployment handles pickled, never as JSON)."""
    merged = [result for answer in answers for result in answer]
    merged.sort(key=lambda result: (result["chamfer"], result["path_id"]))
    return merged[:k]


@serve.deployment(
    name="IndexPartition",
    max_ongoing_requests=PARTITION_MAX_ONGOING,
    graceful_shutdown_timeout_s=SHUTDOWN_DRAIN_S,
    graceful_shutdown_wait_loop_s=SHUTDOWN_POLL_S,
    ray_actor_options={"num_cpus": 1, "runtime_env": {"env_vars": REPLICA_ENV}},
)
class IndexPartition:
    """One partition of the retrieval index: the curated shards numbered `part` modulo `parts`.

    Called by the gateway (`LinksApi`) through its deployment handle, never over HTTP. It opens
    (or builds and saves, under `_links/index/part-P-of-N/`) its part once, warms it, and
    answers each query with its own top k, as a whole index over its paths would.
    """

    def __init__(self, root: str, part: int, parts: int) -> None:
        keep_replica_grpc_on_loopback()
        use_replica_cpus()
        self.part, self.parts = part, parts
        self._slot = RetrievalSlot(RetrievalIndex.open(root, part=part, parts=parts))

    async def info(self) -> dict[str, int]:
        """`{"part", "parts", "paths"}` of this partition."""
        return {"part": self.part, "parts": self.parts, "paths": len(self._slot.index)}

    async def retrieve(
        self,
        points: np.ndarray,
        k: int,
        min_transmission: float = 0.0,
        max_joints: int | None = None,
    ) -> list[RetrievalResult]:
        """The k best results of this part, best first (`RetrievalIndex.retrieve`), their
        arrays pickled to the gateway as they are."""
        results, _ = await self._slot.retrieve_waited(points, k, min_transmission, max_joints)
        return results

    def __del__(self) -> None:
        if hasattr(self, "_slot"):
            self._slot.close()


@serve.deployment(
    name="LinksApi",
    max_ongoing_requests=GATEWAY_MAX_ONGOING,
    max_queued_requests=GATEWAY_MAX_QUEUED,
    backpressure_config={"status_code": 503, "retry_after_s": RETRY_AFTER_S},
    graceful_shutdown_timeout_s=SHUTDOWN_DRAIN_S,
    graceful_shutdown_wait_loop_s=SHUTDOWN_POLL_S,
    ray_actor_options={"num_cpus": 1, "runtime_env": {"env_vars": REPLICA_ENV}},
)
@serve.ingress(api)
class LinksApi(LinksApiRoutes):
    """The HTTP API of one gateway replica: the retrieval index of `root`, opened once; or,
    given `partitions` (deployment handles of `IndexPartition` 0..N-1, in order), the gateway
    that asks them all and merges their answers, holding no index itself. It answers requests
    for its addresses, localhost and `allowed_hosts` (`serve.http.middleware.HostGuard`)."""

    def __init__(
        self,
        root: str,
        partitions: list[DeploymentHandle] | None = None,
        max_retrievals: int = MAX_RETRIEVALS,
        partition_timeout_s: float = PARTITION_TIMEOUT_S,
        allowed_hosts: tuple[str, ...] = (),
    ) -> None:
        keep_replica_grpc_on_loopback()
        use_replica_cpus()
        allow_host_names(
            allowed_hosts
        )  # for `serve.http.middleware.HostGuard`, from the first request
        self.root = root
        self._admission = Admission(max_retrievals)
        # Refinement runs here, one synthesis at a time (each uses every core itself), at the
        # retrievals' niceness, never in the thread pool health checks and simulations use.
        self._refining = low_priority_thread("links-synthesize")
        self._backend: RetrievalBackend
        if partitions:
            self._backend = PartitionedIndex(list(partitions), partition_timeout_s)
            simulate(*WARM_FOUR_BAR, steps=8)  # loads the solver /api/simulate uses
        else:  # warming the index also loads the solver /api/simulate uses
            self._backend = LocalIndex(RetrievalIndex.open(root))
        # Refinement's kernels, loaded in the thread that runs it, before the first synthesis.
        self._refining.submit(warm_default).result()
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
        if hasattr(self, "_backend"):
            self._backend.close()
        if hasattr(self, "_refining"):
            self._refining.shutdown(wait=False, cancel_futures=True)


class PartitionedIndex(RetrievalBackend):
    """The index split into partitions (`IndexPartition` deployments 0..N-1, by their handles,
    in order): every partition is asked at once for its own top k, and the k best of their
    answers kept (`merge_results`). A partition that is unavailable, or partitions that do
    not all answer within `timeout_s`, are ApiError 503."""

    def __init__(self, partitions: list[DeploymentHandle], timeout_s: float) -> None:
        self.partitions = partitions
        self.timeout_s = timeout_s
        self._paths: list[int] | None = None  # learned from the partitions once

    async def retrieve_waited(
        self,
        points: np.ndarray,
        k: int,
        min_transmission_deg: float,
        max_joints: int | None = None,
    ) -> tuple[list[RetrievalResult], float]:
        """The partitions' answers merged; no wait counted here (retrievals wait in the
        partitions' replicas)."""
        answers = await self._ask_partitions(
            "retrieve", points, k, min_transmission_deg, max_joints
        )
        return merge_results(answers, k), 0.0

    async def health(self) -> dict[str, Any]:
        """The partitions' paths, asked once (a partition's index does not change while it
        serves): in all, and each partition's."""
        if self._paths is None:
            infos = await self._ask_partitions("info")
            self._paths = [info["paths"] for info in infos]
        parts = [{"part": part, "paths": paths} for part, paths in enumerate(self._paths)]
        return {"paths": sum(self._paths), "shards": parts}

    async def _ask_partitions(self, method: str, *args: Any) -> list[Any]:
        """Every partition's answer to `method(*args)`, in order, asked at once; ApiError 503
        if one is unavailable or they do not all answer within `timeout_s`."""
        tasks = [
            asyncio.ensure_future(self._ask_partition(part, getattr(handle, method).remote(*args)))
            for part, handle in enumerate(self.partitions)
        ]
        try:
            return await asyncio.wait_for(asyncio.gather(*tasks), self.timeout_s)
        except TimeoutError:
            raise busy(f"the index partitions did not answer within {self.timeout_s:g} s") from None
        finally:
            for task in tasks:  # after a failure, stop asking the others
                task.cancel()

    async def _ask_partition(self, part: int, response: DeploymentResponse) -> Any:
        """One partition's answer; its failures as ApiErrors: 503 for a partition that is not
        there now, 400 for a query it refuses, else 500 (logged by type, never the request)."""
        parts = len(self.partitions)
        try:
            return await response
        except asyncio.CancelledError:  # another part failed, or time ran out: stop this one
            response.cancel()
            raise
        except PARTITION_UNAVAILABLE as exc:
            logger.warning(
                "links-ray API: index partition %d of %d unavailable (%s)",
                part,
                parts,
                type(exc).__name__,
            )
            raise busy(f"index partition {part} of {parts} is unavailable") from None
        except RayTaskError as exc:  # the partition's own exception
            if isinstance(exc.cause, ValueError):
                raise ApiError(400, str(exc.cause)) from None
            logger.error(
                "links-ray API: index partition %d of %d failed with %s",
                part,
                parts,
                type(exc.cause).__name__,
            )
            raise ApiError(500, "internal error") from None
