"""`links import-release` on Ray: the shards of an import of the LINKS release, committed by a
pool of actors (`ShardPool`, as `links generate` runs its shards).

The unit of work is the import's shard: a release batch's mechanisms of one joint count, which
the import commits on its own. But no actor can seek to its batch: the release's files are
sequences of pickles, and a batch's length is known only once it is read, so batch b is reached
only by reading every batch before it. So one reader, in the driver, reads the files in order
and splits each batch into its shards' parts, and each part goes to the actors through the
object store, put once: a part whose actor dies is redone from the same object, by another
actor, and committed exactly once (`links_ray.data.commit`). The driver reads ahead only while
fewer parts wait than there are actors, so memory holds a few parts an actor and the batch
being read, whatever the release's size.

What is read and how a part is imported are given, not imported: the release's files are the
command line's business (docs/design/architecture.md, the layers), so `links import-release`
hands this module the release layer's reader (`release.importer.ReleaseParts`) and its work
(`release.import_shards.import_part`), and the actors load that work as they unpickle it.
Rows depend only on the parts, so they are those of an import in one process.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

import ray
from ray.exceptions import RayTaskError

from links_ray.cluster.actor_pool import ShardPool
from links_ray.cluster.connect import connect
from links_ray.cluster.progress import Progress
from links_ray.data.lease import Lease, LeaseLost, holder_still
from links_ray.data.store import Store

#: Tries of each S3 request inside a shard, to ride out a store's brief refusals.
WRITE_ATTEMPTS = 10

#: Imports one part at a store, calling its fence before each commit; returns its markers.
PartWork = Callable[[Store, Any, Callable[[], None]], dict]


class Part(Protocol):
    """What the driver needs of a part: its shard, and how many mechanisms it counts for."""

    shard_id: int
    mechanisms: int


class Parts(Protocol):
    """The parts an import has left, read as they are iterated, and the progress they make:
    `total` mechanisms (None while unknown; an estimate until `exact`), `done` before the run."""

    total: int | None
    exact: bool
    done: int

    def __iter__(self) -> Iterator[Any]: ...


@dataclass(frozen=True)
class _Unit:
    """A part in the object store, as the pool queues it."""

    shard_id: int
    mechanisms: int
    part: ray.ObjectRef


@ray.remote(num_cpus=1, max_restarts=0)
class ReleaseImportActor:
    """Imports and commits parts of one import."""

    def __init__(self, uri: str, lease_token: str, work: PartWork) -> None:
        self.store = Store.open(uri, attempts=WRITE_ATTEMPTS)
        self.lease_token = lease_token
        self.work = work

    def ready(self) -> None:
        """Answers once the actor runs: placed on a CPU, its store open."""

    def run_shard(self, unit: _Unit) -> dict:
        """Import and commit the part of `unit`; returns its markers."""
        return self.work(self.store, ray.get(unit.part), self._still_ours)

    def _still_ours(self) -> None:
        # An actor outliving its driver must not commit beside the run that took the root over.
        if not holder_still(self.store, "writer", self.lease_token):
            raise LeaseLost(f"{self.store.uri}: the import this actor works for lost the root")


def import_on_ray(
    store: Store,
    lease: Lease,
    parts: Parts,
    work: PartWork,
    workers: int | None = None,
    address: str | None = None,
    progress: bool = True,
    starting: Callable[[], None] | None = None,
) -> tuple[list[dict], int]:
    """Import every part of `parts` into `store` on Ray, `work` on each in an actor, while
    `lease` holds the root; returns the parts' markers and the most actors that ran at once.

    `workers` caps the actors (default: one per CPU of the cluster at `address`, or of a local
    one). Ray starts only once the first part is read: with nothing left to do, or a release
    unreadable from its first batch, it never does (`starting` is called just before). A
    progress line counts the release's mechanisms (`cluster.progress`). A file or part that
    cannot be read (ValueError) stops the reading; the parts read before it are finished, then
    it is raised, in one line.
    """
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    reading = iter(parts)
    first = next(reading, None)
    if first is None:
        return [], 0
    if starting is not None:
        starting()
    connect(address)
    meter = Progress(total=None, done=parts.done, unit="mechanisms", enabled=progress)
    meter.estimate(parts.total, parts.exact)
    todo: deque[_Unit] = deque([_put(first)])
    cpus = int(ray.cluster_resources().get("CPU", 1))
    actors = min(workers or cpus, cpus)  # the pool's size once it has grown
    uri, token = store.uri, lease.token
    pool = ShardPool(lambda: ReleaseImportActor.remote(uri, token, work), workers, role="import")
    done: list[dict] = []
    failure: ValueError | None = None
    try:
        while todo or pool.busy() or (reading is not None and failure is None):
            if lease.lost:
                lease.confirm()  # raises: another run owns the root now
            # Read ahead while fewer parts wait than there are actors to take them.
            while reading is not None and len(todo) < max(pool.size(), actors):
                try:
                    part = next(reading, None)
                except ValueError as exc:
                    failure, reading = exc, None
                    break
                meter.estimate(parts.total, parts.exact)
                if part is None:
                    reading = None
                    break
                todo.append(_put(part))
            if not todo and not pool.busy():
                break
            pool.resize(work_left=len(todo))
            pool.submit(todo)
            try:
                finished = pool.collect(todo)
            except RayTaskError as exc:
                if not isinstance(exc.cause, ValueError):
                    raise
                # A part the release holds wrongly: the parts under way are finished first.
                failure, reading = failure or exc.cause, None
                continue
            for unit, markers in finished:
                done.append(markers)
                meter.advance(unit.mechanisms)
    except BaseException:
        pool.shutdown()
        meter.close(final=False)
        raise
    pool.shutdown()
    meter.close(final=failure is None)
    if failure is not None:
        raise failure
    return done, pool.peak


def _put(part: Part) -> _Unit:
    return _Unit(part.shard_id, part.mechanisms, ray.put(part))
