"""The generation service on Ray: a pool of actors turns shards into committed Parquet files.

Each `GeneratorActor` owns the compiled engine (numba kernels loaded once per process) and
handles one shard at a time: it draws the shard's topologies and positions, streams record
batches into hidden files and commits them (`links_ray.storage`). The driver keeps the pool as
large as the cluster's CPUs allow (up to `workers`), growing it when nodes join; a shard whose
actor dies, with its node or by a kill, goes back to the queue and is redone elsewhere. Since
rows depend only on the plan and a redone shard replaces its files, the result is the same
whatever happens on the way, and running the same command again finishes an interrupted run.
"""

from __future__ import annotations

import os
import time
from collections import deque
from dataclasses import asdict

import ray
from ray.exceptions import ActorDiedError, ActorUnavailableError, RayActorError

from links_ray.progress import Progress
from links_ray.shards import GenerationPlan, Shard, generate_shard
from links_ray.storage import META, ShardWriter, Store, StoreError

#: Shards queued on an actor at once: one running, one ready, so no actor waits on the driver.
SHARDS_IN_FLIGHT = 2
#: How often the driver looks for new CPUs in the cluster.
RESIZE_EVERY_S = 2.0
#: Tries of each S3 request inside a shard, to ride out a store's brief refusals.
WRITE_ATTEMPTS = 10
#: Times a shard may fail with a storage error before the run stops.
SHARD_ATTEMPTS = 3


@ray.remote(num_cpus=1, max_restarts=0)
class GeneratorActor:
    """Generates and commits shards of one run."""

    def __init__(self, uri: str, plan: dict) -> None:
        self.store = Store.open(uri, attempts=WRITE_ATTEMPTS)
        self.plan = GenerationPlan(**plan)

    def run_shard(self, shard: Shard) -> dict:
        """Generate, write and commit `shard`; returns its commit marker."""
        writer = ShardWriter(self.store, shard.shard_id, shard.n_joints)
        try:
            stats = generate_shard(self.plan, shard, writer.write)
            return writer.commit(stats)
        except BaseException:
            writer.abort()
            raise


def connect(address: str | None = None) -> None:
    """Join the Ray cluster at `address` (or RAY_ADDRESS, as under `ray job submit`), or start
    a local one on this machine's CPUs."""
    if ray.is_initialized():
        return
    if address or os.environ.get("RAY_ADDRESS"):
        ray.init(address=address, logging_level="WARNING")
    else:
        ray.init(include_dashboard=False, logging_level="WARNING")


def generate(
    out: str,
    mechanisms: int,
    seed: int = 0,
    workers: int | None = None,
    sampler: str = "sequential",
    address: str | None = None,
    progress: bool = True,
    topologies_per_shard: int | None = None,
) -> dict:
    """Generate `mechanisms` valid mechanisms into `out` on Ray; returns the run summary.

    Resumable: shards committed by an earlier run of the same plan are kept, the rest are made.
    """
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    extra = {} if topologies_per_shard is None else {"topologies_per_shard": topologies_per_shard}
    plan = GenerationPlan(seed=seed, mechanisms=mechanisms, sampler=sampler, **extra)
    store = Store.open(out)
    _claim(store, plan)
    shards = plan.shards()
    committed = store.committed_shards()
    todo = deque(shard for shard in shards if shard.shard_id not in committed)

    connect(address)
    start = time.perf_counter()
    meter = Progress(
        total=plan.mechanisms,
        done=sum(marker["stats"]["mechanisms"] for marker in committed.values()),
        unit="mechanisms",
        enabled=progress,
    )
    pool = _Pool(out, plan, workers)
    try:
        while todo or pool.busy():
            pool.resize(work_left=len(todo))
            pool.submit(todo)
            for shard, marker in pool.collect(todo):
                committed[shard.shard_id] = marker
                meter.advance(marker["stats"]["mechanisms"])
    finally:
        pool.shutdown()
        meter.close()
    store.remove_uncommitted()
    summary = summarize(plan, committed, store.uri, time.perf_counter() - start, pool.peak)
    store.write_json(f"{META}/summary.json", summary)
    return summary


def _claim(store: Store, plan: GenerationPlan) -> None:
    """Record the plan at the root, or check it matches the plan already recorded there."""
    recorded = store.read_json(f"{META}/run.json")
    if recorded is None:
        store.write_json(f"{META}/run.json", plan.config())
    elif recorded != plan.config():
        differ = sorted(k for k in plan.config() if recorded.get(k) != plan.config()[k])
        raise StoreError(
            f"{store.uri} holds another run ({', '.join(f'{k}={recorded.get(k)}' for k in differ)}"
            "); use a new --out or the same options"
        )


class _Pool:
    """Generator actors sized to the cluster, each fed up to SHARDS_IN_FLIGHT shards."""

    def __init__(self, uri: str, plan: GenerationPlan, workers: int | None) -> None:
        self.uri = uri
        self.plan = asdict(plan)
        self.workers = workers
        self.actors: list[ray.actor.ActorHandle] = []
        self.in_flight: dict[ray.ObjectRef, tuple[ray.actor.ActorHandle, Shard]] = {}
        self.peak = 0
        self.failures: dict[int, int] = {}
        self._resized = 0.0

    def busy(self) -> bool:
        return bool(self.in_flight)

    def resize(self, work_left: int) -> None:
        """Add actors while the cluster has CPUs for them (it may have grown)."""
        now = time.monotonic()
        if now - self._resized < RESIZE_EVERY_S and self.actors:
            return
        self._resized = now
        cpus = int(ray.cluster_resources().get("CPU", 1))
        wanted = min(self.workers or cpus, cpus, work_left + len(self.in_flight))
        while len(self.actors) < max(wanted, 1 if work_left else 0):
            self.actors.append(GeneratorActor.remote(self.uri, self.plan))
        self.peak = max(self.peak, len(self.actors))

    def submit(self, todo: deque[Shard]) -> None:
        load = {actor: 0 for actor in self.actors}
        for actor, _ in self.in_flight.values():
            if actor in load:  # a dead actor's other shards are still being reported
                load[actor] += 1
        for actor in self.actors:
            while todo and load[actor] < SHARDS_IN_FLIGHT:
                shard = todo.popleft()
                self.in_flight[actor.run_shard.remote(shard)] = (actor, shard)
                load[actor] += 1

    def collect(self, todo: deque[Shard]) -> list[tuple[Shard, dict]]:
        """Finished shards; shards of dead actors go back to the front of `todo`."""
        ready, _ = ray.wait(list(self.in_flight), num_returns=1, timeout=1.0)
        done = []
        for ref in ready:
            actor, shard = self.in_flight.pop(ref)
            try:
                done.append((shard, ray.get(ref)))
            except (RayActorError, ActorDiedError, ActorUnavailableError):
                todo.appendleft(shard)
                if actor in self.actors:
                    self.actors.remove(actor)
                    ray.kill(actor, no_restart=True)
            except ray.exceptions.RayTaskError as exc:
                cause = exc.cause
                if not isinstance(cause, OSError):
                    raise
                failures = self.failures[shard.shard_id] = self.failures.get(shard.shard_id, 0) + 1
                if failures >= SHARD_ATTEMPTS:
                    raise StoreError(
                        f"shard {shard.shard_id} failed {failures} times writing to the store; "
                        f"last: {str(cause).splitlines()[0]}"
                    ) from None
                todo.append(shard)
        return done

    def shutdown(self) -> None:
        for actor in self.actors:
            ray.kill(actor, no_restart=True)
        self.actors.clear()


def summarize(
    plan: GenerationPlan, markers: dict[int, dict], uri: str, seconds: float, workers: int
) -> dict:
    """The run summary: counts, candidates per valid mechanism by joint count, throughput."""
    by_size: dict[int, dict] = {}
    rows = {"mechanisms": 0, "simulations": 0, "negatives": 0}
    compute_s = 0.0
    for marker in markers.values():
        stats = marker["stats"]
        entry = by_size.setdefault(
            marker["n_joints"], {"topologies": 0, "mechanisms": 0, "candidates": 0, "valid": 0}
        )
        for key in entry:
            entry[key] += stats[key]
        for table, count in marker["rows"].items():
            rows[table] += count
        compute_s += stats["seconds"]
    for entry in by_size.values():
        entry["candidates_per_valid"] = entry["candidates"] / entry["valid"]
    return {
        "out": uri,
        "plan": plan.config(),
        "complete": rows["mechanisms"] == plan.mechanisms,
        "rows": rows,
        "shards": len(markers),
        "by_joint_count": {str(n): by_size[n] for n in sorted(by_size)},
        "candidates_per_valid_meaning": (
            "complete position sets tried per valid one"
            if plan.sampler == "rejection"
            else "sequential attempts (restarts included) per valid set"
        ),
        "seconds": seconds,
        "workers": workers,
        "mechanisms_per_second": rows["mechanisms"] / seconds if seconds else None,
        "valid_per_core_second": rows["mechanisms"] / compute_s if compute_s else None,
    }
