"""A pool of Ray actors that commit shards: sized to the cluster and grown when it grows, a
shard whose actor dies queued again at the front, a shard that fails on storage errors retried a
bounded number of times. `links generate` and `links import-release` run their shards on it;
each shard is committed exactly once by the commit protocol (`links_ray.data.commit`), whatever
the pool redoes.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from typing import Any

import ray
from ray.actor import ActorHandle
from ray.exceptions import ActorDiedError, ActorUnavailableError, RayActorError

from links_ray.data.store import StoreError

#: Shards queued on an actor at once: one running, one ready, so no actor waits on the driver.
SHARDS_IN_FLIGHT = 2
#: How often the driver looks for new CPUs in the cluster.
RESIZE_EVERY_S = 2.0
#: Times a shard may fail with a storage error before the run stops.
SHARD_ATTEMPTS = 3


class ShardPool:
    """Actors sized to the cluster, each fed up to SHARDS_IN_FLIGHT shards once it runs. An
    actor waiting for a CPU (others' work may hold the cluster's) is given none: its shards
    would wait with it while the running actors idle.

    `make_actor()` starts one actor: a Ray actor with `ready()` and `run_shard(shard)`, which
    commits `shard` (anything with a `shard_id`) and returns its result. `role` names the
    actors in the error that stops a run whose actors keep dying."""

    def __init__(
        self, make_actor: Callable[[], ActorHandle], workers: int | None, role: str
    ) -> None:
        self.make_actor = make_actor
        self.role = role
        self.workers = workers
        self.load: dict[ActorHandle, int] = {}  # running actors: shards in flight
        self.starting: dict[ray.ObjectRef, ActorHandle] = {}  # by their ready() call
        self.in_flight: dict[ray.ObjectRef, tuple[ActorHandle, Any]] = {}
        self.peak = 0
        self.failures: dict[int, int] = {}
        self.deaths_since_progress = 0
        self._resized = 0.0
        if workers:
            _request_cpus(workers)  # lets an autoscaling cluster grow towards `workers`

    def busy(self) -> bool:
        """Whether shards are in flight."""
        return bool(self.in_flight)

    def size(self) -> int:
        """The actors running or starting."""
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
            actor = self.make_actor()
            self.starting[actor.ready.remote()] = actor

    def submit(self, todo: deque[Any]) -> None:
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

    def collect(self, todo: deque[Any]) -> list[tuple[Any, Any]]:
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

    def _bury(self, actor: ActorHandle, exc: Exception) -> None:
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
                f"{self.deaths_since_progress} {self.role} actors died without finishing a shard; "
                f"last: {reason}"
            )

    def _retry(self, shard: Any, exc: ray.exceptions.RayTaskError, todo: deque[Any]) -> None:
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
        """Kill every actor, and take the results of shards still in flight."""
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
