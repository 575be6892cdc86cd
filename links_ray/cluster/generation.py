"""The generation service on Ray: a pool of actors turns shards into committed Parquet files.

Each `GeneratorActor` owns the compiled engine (its kernels loaded once per process) and
handles one shard at a time: it draws the shard's topologies and positions, streams record
batches into hidden files and commits them (`links_ray.data.store`). The driver keeps the pool as
large as the cluster's CPUs allow (up to `workers`), growing it when nodes join; a shard whose
actor dies, with its node or by a kill, goes back to the queue and is redone elsewhere. Since
rows depend only on the plan and exactly one attempt of a shard commits (`links_ray.data.commit`),
the result is the same whatever happens on the way, and running the same command again finishes
an interrupted run.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import asdict, replace

import ray
from ray.exceptions import ActorDiedError, ActorUnavailableError, RayActorError

from links_ray.cluster.connect import connect
from links_ray.cluster.progress import Progress
from links_ray.data.commit import committed_shards, remove_uncommitted
from links_ray.data.lease import Lease, LeaseLost, holder_still
from links_ray.data.schemas import GENERATION_TABLES
from links_ray.data.shards import GenerationPlan, Shard, write_shard
from links_ray.data.store import META, Store, StoreError, refuse_imported
from links_ray.engine.topology import TOPOLOGY_RULES

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

    def __init__(self, uri: str, plan: dict, lease_token: str) -> None:
        self.store = Store.open(uri, attempts=WRITE_ATTEMPTS)
        self.plan = GenerationPlan(**plan)
        self.lease_token = lease_token

    def ready(self) -> None:
        """Answers once the actor runs: placed on a CPU, its store open."""

    def run_shard(self, shard: Shard) -> dict:
        """Generate, write and commit `shard`; returns its commit marker."""
        return write_shard(self.store, self.plan, shard, fence=self._still_ours)

    def _still_ours(self) -> None:
        # An actor outliving its driver must not commit beside the run that took the root over.
        if not holder_still(self.store, "writer", self.lease_token):
            raise LeaseLost(f"{self.store.uri}: the run this actor works for lost the root")


def generate(
    out: str,
    mechanisms: int,
    seed: int = 0,
    workers: int | None = None,
    sampler: str = "sequential",
    address: str | None = None,
    progress: bool = True,
    topologies_per_shard: int | None = None,
    tables: str | Iterable[str] = GENERATION_TABLES,
    topology_rules: str = TOPOLOGY_RULES[0],
    min_transmission_deg: float = 0.0,
    starting: Callable[[], None] | None = None,
) -> dict:
    """Generate `mechanisms` valid mechanisms into `out` on Ray; returns the run summary.

    `topology_rules` picks the topology generator (`links`, the LINKS release's rules, or
    `feasible`: engine.topology); `min_transmission_deg` above 0 keeps only mechanisms whose
    least transmission angle reaches it (0, the default, is the paper's distribution).

    `tables` are the tables written: `mechanisms` and any of `simulations` and `negatives`
    (names, or one comma-separated string). Resumable: shards committed by an earlier run of
    the same plan are kept, the rest are made; when none is left the saved summary is
    returned, with `nothing_to_do`, and Ray is not started. `starting` is called just before
    Ray starts, only when there is work.
    """
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    extra = {} if topologies_per_shard is None else {"topologies_per_shard": topologies_per_shard}
    plan = GenerationPlan(
        seed=seed,
        mechanisms=mechanisms,
        sampler=sampler,
        tables=tables,
        topology_rules=topology_rules,
        min_transmission_deg=min_transmission_deg,
        **extra,
    )
    store = Store.open(out)
    with Lease.acquire(store, "writer", "links generate") as lease:
        # What a run recorded before an option existed did: all tables, the first topology
        # generator, no transmission threshold.
        before_options = {
            "tables": list(GENERATION_TABLES),
            "topology_rules": "feasible",
            "min_transmission_deg": 0.0,
            "grown_from": [],
        }
        refuse_imported(store)
        plan = _plan_on_root(store, plan, before_options)
        committed = committed_shards(store, "shards")
        remove_uncommitted(store, "shards", committed)
        todo = deque(shard for shard in plan.shards() if shard.shard_id not in committed)
        saved = None if todo else store.read_json(f"{META}/summary.json")
        if saved is not None and saved.get("complete"):
            # A finished run asked again: its summary, without starting Ray for nothing.
            return {**saved, "nothing_to_do": True}

        if starting is not None:
            starting()
        connect(address)
        start = time.perf_counter()
        meter = Progress(
            total=plan.mechanisms,
            done=sum(marker["stats"]["mechanisms"] for marker in committed.values()),
            unit="mechanisms",
            enabled=progress,
        )
        pool = _Pool(out, plan, workers, lease.token)
        try:
            while todo or pool.busy():
                if lease.lost:
                    lease.confirm()  # raises: another run owns the root now
                pool.resize(work_left=len(todo))
                pool.submit(todo)
                for shard, marker in pool.collect(todo):
                    committed[shard.shard_id] = marker
                    meter.advance(marker["stats"]["mechanisms"])
        finally:
            pool.shutdown()
            meter.close()
        lease.confirm()
        remove_uncommitted(store, "shards", committed)
        summary = summarize(plan, committed, store.uri, time.perf_counter() - start, pool.peak)
        store.write_json(f"{META}/summary.json", summary)
    return summary


def _plan_on_root(store: Store, asked: GenerationPlan, defaults: dict) -> GenerationPlan:
    """The plan a run asking for `asked` carries out at `store`, recorded in `run.json`: `asked`
    on a new root, the recorded plan to resume it, or the recorded plan grown to
    `asked.mechanisms` when that is more (StoreError if the root holds another run)."""
    recorded = store.read_json(f"{META}/run.json")
    if recorded is not None:
        recorded = {**defaults, **recorded}
        try:
            held = GenerationPlan(**recorded)
        except (TypeError, ValueError):
            held = None  # unreadable as a plan: claim names what differs
        if held is not None and replace(held, mechanisms=asked.mechanisms, grown_from=()) == (
            replace(asked, grown_from=())
        ):
            try:
                grown = held.grown_to(asked.mechanisms)
            except ValueError as exc:
                raise StoreError(f"{store.uri}: {exc}") from None
            if grown != held:
                store.write_json(f"{META}/run.json", grown.config())
            return grown
    store.claim(f"{META}/run.json", asked.config(), defaults=defaults)
    return asked


class _Pool:
    """Generator actors sized to the cluster, each fed up to SHARDS_IN_FLIGHT shards once it
    runs. An actor waiting for a CPU (others' work may hold the cluster's) is given none: its
    shards would wait with it while the running actors idle."""

    def __init__(
        self, uri: str, plan: GenerationPlan, workers: int | None, lease_token: str
    ) -> None:
        self.uri = uri
        self.plan = asdict(plan)
        self.lease_token = lease_token
        self.workers = workers
        self.load: dict[ray.actor.ActorHandle, int] = {}  # running actors: shards in flight
        self.starting: dict[ray.ObjectRef, ray.actor.ActorHandle] = {}  # by their ready() call
        self.in_flight: dict[ray.ObjectRef, tuple[ray.actor.ActorHandle, Shard]] = {}
        self.peak = 0
        self.failures: dict[int, int] = {}
        self.deaths_since_progress = 0
        self._resized = 0.0
        if workers:
            _request_cpus(workers)  # lets an autoscaling cluster grow towards `workers`

    def busy(self) -> bool:
        return bool(self.in_flight)

    def size(self) -> int:
        return len(self.load) + len(self.starting)

    def resize(self, work_left: int) -> None:
        """Add actors while the cluster has CPUs for them (it may have grown).

        Actors are only made for CPUs that exist; one waiting for a CPU that other work holds
        is given shards once it runs (`submit`).
        """
        now = time.monotonic()
        if now - self._resized < RESIZE_EVERY_S and self.size():
            return
        self._resized = now
        cpus = int(ray.cluster_resources().get("CPU", 1))
        wanted = min(self.workers or cpus, cpus, work_left + len(self.in_flight))
        while self.size() < max(wanted, 1 if work_left else 0):
            actor = GeneratorActor.remote(self.uri, self.plan, self.lease_token)
            self.starting[actor.ready.remote()] = actor

    def submit(self, todo: deque[Shard]) -> None:
        """Queue shards of `todo` on the running actors, after taking in those that started."""
        if self.starting:
            started, _ = ray.wait(list(self.starting), num_returns=len(self.starting), timeout=0)
            for ref in started:
                actor = self.starting[ref]
                try:
                    ray.get(ref)
                except (RayActorError, ActorDiedError, ActorUnavailableError) as exc:
                    self._bury(actor, exc)
                    continue
                self.load[actor] = 0
                del self.starting[ref]
            self.peak = max(self.peak, len(self.load))
        for actor, load in self.load.items():
            while todo and load < SHARDS_IN_FLIGHT:
                shard = todo.popleft()
                self.in_flight[actor.run_shard.remote(shard)] = (actor, shard)
                load += 1
            self.load[actor] = load

    def collect(self, todo: deque[Shard]) -> list[tuple[Shard, dict]]:
        """Finished shards; shards of dead actors go back to the front of `todo`. Also returns,
        with none, when an actor starts."""
        waiting = [*self.in_flight, *self.starting]
        if not waiting:
            return []
        ready, _ = ray.wait(waiting, num_returns=1, timeout=1.0)
        if ready and self.in_flight:  # take every shard that has finished, not just the first
            ready, _ = ray.wait(list(self.in_flight), num_returns=len(self.in_flight), timeout=0)
        else:
            ready = []  # nothing, or an actor started: `submit` takes it in
        done = []
        for ref in ready:
            actor, shard = self.in_flight.pop(ref)
            try:
                done.append((shard, ray.get(ref)))
                self.load[actor] -= 1
                self.deaths_since_progress = 0
            except (RayActorError, ActorDiedError, ActorUnavailableError) as exc:
                todo.appendleft(shard)
                self._bury(actor, exc)
            except ray.exceptions.RayTaskError as exc:
                self.load[actor] -= 1
                self._retry(shard, exc, todo)
        return done

    def _bury(self, actor: ray.actor.ActorHandle, exc: Exception) -> None:
        """Forget a dead actor; stop the run if actors die again and again with no progress."""
        if actor in self.load:
            del self.load[actor]
        else:
            refs = [ref for ref, starting in self.starting.items() if starting == actor]
            if not refs:
                return  # its other shards report the same death
            for ref in refs:
                del self.starting[ref]
        ray.kill(actor, no_restart=True)
        self.deaths_since_progress += 1
        if self.deaths_since_progress > max(4, 2 * self.peak):
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise RuntimeError(
                f"{self.deaths_since_progress} generator actors died without finishing a shard; "
                f"last: {reason}"
            )

    def _retry(self, shard: Shard, exc: ray.exceptions.RayTaskError, todo: deque[Shard]) -> None:
        """Queue a shard again after a storage error; a bug or repeated failure ends the run."""
        cause = exc.cause
        if not isinstance(cause, OSError):
            raise exc
        failures = self.failures[shard.shard_id] = self.failures.get(shard.shard_id, 0) + 1
        if failures >= SHARD_ATTEMPTS:
            raise StoreError(
                f"shard {shard.shard_id} failed {failures} times writing to the store; "
                f"last: {str(cause).splitlines()[0]}"
            ) from None
        todo.append(shard)

    def shutdown(self) -> None:
        for actor in [*self.load, *self.starting.values()]:
            ray.kill(actor, no_restart=True)
        self.load.clear()
        self.starting.clear()
        # Take the errors of shards still in flight: Ray prints an error nobody took when it
        # drops its reference, after the run's own one-line message.
        refs = list(self.in_flight)
        self.in_flight.clear()
        ready, _ = ray.wait(refs, num_returns=len(refs), timeout=5.0) if refs else ([], [])
        for ref in ready:
            try:
                ray.get(ref)
            except Exception:  # the run is over; its error is already on its way up
                pass
        if self.workers:
            _request_cpus(0)


def _request_cpus(cpus: int) -> None:
    """Ask the cluster's autoscaler, if it has one, for `cpus` CPUs in all."""
    try:
        from ray.autoscaler.sdk import request_resources

        request_resources(num_cpus=cpus)
    except Exception:  # no autoscaler here: the request has no one to read it
        pass


#: The counts each shard's marker holds (data.shards.generate_shard), summed by joint count.
SHARD_COUNTS = (
    "topologies",
    "mechanisms",
    "candidates",
    "valid",
    "below_transmission",
    "abandoned",
)


def summarize(
    plan: GenerationPlan, markers: dict[int, dict], uri: str, seconds: float, workers: int
) -> dict:
    """The run summary: counts, candidates per valid mechanism by joint count, throughput."""
    by_size: dict[int, dict] = {}
    rows = dict.fromkeys(plan.tables, 0)
    compute_s = 0.0
    for marker in markers.values():
        stats = marker["stats"]
        entry = by_size.setdefault(
            marker["n_joints"],
            dict.fromkeys(SHARD_COUNTS, 0),
        )
        for key in entry:
            entry[key] += stats.get(key, 0)
        for table, count in marker["rows"].items():
            rows[table] += count  # a table with no rows in a shard is absent from its marker
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
