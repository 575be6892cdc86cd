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

from links_ray.cluster.actor_pool import ShardPool
from links_ray.cluster.connect import connect
from links_ray.cluster.progress import Progress
from links_ray.data.commit import committed_shards, remove_uncommitted
from links_ray.data.generation import GenerationPlan, Shard, write_shard
from links_ray.data.lease import Lease, LeaseLost, holder_still
from links_ray.data.schemas import GENERATION_TABLES
from links_ray.data.store import META, Store, StoreError, refuse_imported
from links_ray.engine.kinematics.topology import TOPOLOGY_RULES

#: Tries of each S3 request inside a shard, to ride out a store's brief refusals.
WRITE_ATTEMPTS = 10


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


#: What a run recorded before an option existed did: all tables, the first topology generator,
#: no transmission threshold, no extension.
RECORD_DEFAULTS = {
    "tables": list(GENERATION_TABLES),
    "topology_rules": "feasible",
    "min_transmission_deg": 0.0,
    "extended_from": [],
}


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
    `feasible`: engine.kinematics.topology); `min_transmission_deg` above 0 keeps only mechanisms
    whose least transmission angle reaches it (0, the default, is the paper's distribution).

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
        refuse_imported(store)
        plan = plan_on_root(store, plan, RECORD_DEFAULTS)
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
        config = asdict(plan)
        pool = ShardPool(
            lambda: GeneratorActor.remote(out, config, lease.token), workers, role="generator"
        )
        made_now = 0  # mechanisms made by this run: a resumed run's rate counts only these
        try:
            while todo or pool.busy():
                if lease.lost:
                    lease.confirm()  # raises: another run owns the root now
                pool.resize(work_left=len(todo))
                pool.submit(todo)
                for shard, marker in pool.collect(todo):
                    committed[shard.shard_id] = marker
                    made_now += marker["stats"]["mechanisms"]
                    meter.advance(marker["stats"]["mechanisms"])
        finally:
            pool.shutdown()
            meter.close()
        lease.confirm()
        remove_uncommitted(store, "shards", committed)
        seconds = time.perf_counter() - start
        summary = summarize(plan, committed, store.uri, seconds, pool.peak, made_now)
        store.write_json(f"{META}/summary.json", summary)
    return summary


def plan_on_root(store: Store, asked: GenerationPlan, defaults: dict) -> GenerationPlan:
    """The plan a run asking for `asked` carries out at `store`, recorded in `run.json`: `asked`
    on a new root, the recorded plan to resume it, or the recorded plan extended to
    `asked.mechanisms` when that is more (StoreError if the root holds another run)."""
    recorded = store.read_json(f"{META}/run.json")
    if recorded is not None:
        if "grown_from" in recorded:  # the key's name in roots written before 0.5
            recorded["extended_from"] = recorded.pop("grown_from")
        recorded = {**defaults, **recorded}
        try:
            held = GenerationPlan(**recorded)
        except (TypeError, ValueError):
            held = None  # unreadable as a plan: claim names what differs
        if held is not None and replace(held, mechanisms=asked.mechanisms, extended_from=()) == (
            replace(asked, extended_from=())
        ):
            try:
                extended = held.extended_to(asked.mechanisms)
            except ValueError as exc:
                raise StoreError(f"{store.uri}: {exc}") from None
            if extended != held:
                store.write_json(f"{META}/run.json", extended.config())
            return extended
    store.claim(f"{META}/run.json", asked.config(), defaults=defaults)
    return asked


#: The counts each shard's marker holds (data.generation.generate_shard), summed by joint count.
SHARD_COUNTS = (
    "topologies",
    "mechanisms",
    "candidates",
    "valid",
    "below_transmission",
    "abandoned",
)


def summarize(
    plan: GenerationPlan,
    markers: dict[int, dict],
    uri: str,
    seconds: float,
    workers: int,
    made_now: int,
) -> dict:
    """The run summary: counts over the whole root, candidates per valid mechanism by joint
    count, and throughput: `mechanisms_per_second` is this run's (`made_now` mechanisms in
    `seconds`: a resumed run's earlier rows took no time of it), `valid_per_core_second` the
    root's (all rows over the seconds every shard's actor took)."""
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
        "mechanisms_this_run": made_now,
        "mechanisms_per_second": made_now / seconds if seconds else None,
        "valid_per_core_second": rows["mechanisms"] / compute_s if compute_s else None,
    }
