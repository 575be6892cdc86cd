"""Admission: how many retrievals and syntheses a gateway replica holds, and in what order
syntheses take its one refinement thread.

A replica holds at most `max_retrievals` retrievals (`MAX_RETRIEVALS` by default) and
`MAX_SYNTHESES` syntheses, running or waiting; one more is refused at once with 503 and
`Retry-After` (`busy`), so that a burst neither piles up without bound nor holds what health
checks and simulations need. Syntheses then wait in line (`Admission.line`, one `Place` each)
for the refinement thread, which refines one at a time; one that would wait longer than its
own budget is refused 503 too.

Retrievals run in a thread of their own, one at a time, beside the index they search
(`backend.RetrievalSlot`). Both threads run at `RETRIEVAL_NICENESS`, below the event loop that
answers health checks. Drawings (`/api/curve`) are read with tokens and threads of their own
(`CurveReads`), never the thread pool's that simulations, analyses and exports share. Nothing here
imports Ray: the routes (`serve.http.routes`) and the deployments (`serve.deployments`) both use it.
"""

from __future__ import annotations

import asyncio
import math
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from links_ray.interop.curve_files import Curve
from links_ray.interop.curve_limits import CURVE_READER_WAIT_S, CURVE_READERS
from links_ray.interop.curve_worker import read_curve_isolated
from links_ray.serve.http.limits import (
    MAX_CURVE_READS,
    MAX_RETRIEVALS,
    MAX_SYNTHESES,
    RETRY_AFTER_S,
)
from links_ray.serve.http.responses import ApiError

#: Retrievals are the throughput work; health checks and simulations must be answered at
#: once. So the thread that retrieves, and the kernels' worker threads it starts, run at this
#: niceness (Linux niceness is per thread, and new threads inherit it), below the replica's
#: event loop and thread pool and any gateway on the same node, still above Ray's workers.
RETRIEVAL_NICENESS = 5


def busy(message: str, retry_after: float = RETRY_AFTER_S) -> ApiError:
    """503 with `Retry-After` (whole seconds, at least RETRY_AFTER_S): come back then."""
    seconds = max(RETRY_AFTER_S, math.ceil(retry_after))
    return ApiError(503, message, headers={"Retry-After": str(seconds)})


class Place:
    """A synthesis's place in the line for a replica's refinement thread: its refinement
    budget (None for counted work, whose length is unknown), when its refinement began, and the
    future set when the thread is its own."""

    def __init__(self, budget: float | None) -> None:
        self.budget = budget
        self.began: float | None = None
        self.ready: asyncio.Future[None] = asyncio.get_running_loop().create_future()


class Admission:
    """The retrievals and syntheses one replica holds, and the line of syntheses for its
    refinement thread. Only the event loop's thread uses it, so plain counts suffice."""

    def __init__(self, max_retrievals: int = MAX_RETRIEVALS) -> None:
        self.max_retrievals = max_retrievals
        self.retrievals = 0  # running or waiting
        self.syntheses = 0  # running or waiting
        self.line: list[Place] = []  # the first holds the refinement thread
        self.curves = CurveReads()

    def claim_retrieval(self) -> None:
        """Count one more retrieval under way, or refuse it 503 at the limit."""
        if self.retrievals >= self.max_retrievals:
            raise busy(
                f"busy: {self.retrievals} retrievals under way, the most this server "
                f"holds; retry after {RETRY_AFTER_S} s"
            )
        self.retrievals += 1

    def release_retrieval(self) -> None:
        """One retrieval under way fewer."""
        self.retrievals -= 1

    def claim_synthesis(self) -> None:
        """Count one more synthesis under way, or refuse it 503 at MAX_SYNTHESES."""
        if self.syntheses >= MAX_SYNTHESES:
            raise busy(
                f"busy: {self.syntheses} syntheses under way, the most this server holds; "
                f"retry after {RETRY_AFTER_S} s"
            )
        self.syntheses += 1

    def release_synthesis(self, place: Place | None, _: object = None) -> None:
        """One synthesis under way fewer, and its place (if it had one) left; the unused
        argument lets it be a future's done callback."""
        self.syntheses -= 1
        if place is not None:
            self.leave(place)

    def expected_wait(self) -> float | None:
        """Seconds until the syntheses in line end their budgets; None if one does counted work
        (its length is not known beforehand)."""
        now = time.perf_counter()
        wait = 0.0
        for place in self.line:
            if place.budget is None:
                return None
            wait += (
                place.budget if place.began is None else max(0.0, place.began + place.budget - now)
            )
        return wait

    async def wait_for_refiner(self, budget: float | None, patience: float) -> Place:
        """This synthesis's place at the refinement thread, once the ones before it are done;
        503 with `Retry-After` if it would wait longer than `patience` seconds: at once when
        the wait is known beforehand, else once it has waited that long."""
        expected = self.expected_wait()
        if expected is not None and expected > patience:
            raise busy(
                f"busy: the syntheses under way end in about {expected:.1f} s, longer than "
                f"this one may wait ({max(0.0, patience):.1f} s of its budget)",
                retry_after=expected - max(0.0, patience),
            )
        place = Place(budget)
        self.line.append(place)
        if len(self.line) == 1:
            place.ready.set_result(None)
        try:
            await asyncio.wait({place.ready}, timeout=max(0.0, patience))
        except BaseException:  # the client went away: its place, or the thread, goes on
            self.leave(place)
            raise
        if not place.ready.done():
            self.leave(place)
            raise busy(
                f"busy: waited {max(0.0, patience):.1f} s for the syntheses under way, as "
                "long as this one may wait; retry after they end"
            )
        return place

    def leave(self, place: Place) -> None:
        """`place` is done with the refinement thread (or gave up waiting): the next in line
        takes the thread."""
        self.line.remove(place)
        if self.line and not self.line[0].ready.done():
            self.line[0].ready.set_result(None)


class CurveReads:
    """The drawings one replica reads: `readers` at a time, each in a thread of this pool
    waiting on its reader process (`interop.curve_worker`), at most `most` held, reading or
    waiting for a token. One more, or one that finds no token free within `wait_s`, is
    answered 503 with `Retry-After` (`busy`). Only the event loop's thread uses it."""

    def __init__(
        self,
        readers: int = CURVE_READERS,
        most: int = MAX_CURVE_READS,
        wait_s: float = CURVE_READER_WAIT_S,
    ) -> None:
        self.readers = readers
        self.most = most
        self.wait_s = wait_s
        self.held = 0  # reading or waiting
        self.reading = 0
        self._tokens = asyncio.Semaphore(readers)
        self._pool = ThreadPoolExecutor(max_workers=readers, thread_name_prefix="links-curve")

    async def read(self, name: str, text: str, part: str | None) -> Curve:
        """The curve of the file `name` (`read_curve_isolated`), read with one of the tokens:
        503 when none comes free in time, else what the reader raises."""
        if self.held >= self.most:
            raise busy(
                f"busy: {self.held} drawings being read or waiting, the most this server holds"
            )
        self.held += 1
        try:
            await asyncio.wait_for(self._tokens.acquire(), self.wait_s)
        except TimeoutError:
            self.held -= 1
            raise busy(
                f"busy: no curve reader came free within {self.wait_s:g} s (all "
                f"{self.readers} busy)"
            ) from None
        except BaseException:
            self.held -= 1
            raise
        self.reading += 1
        reading = asyncio.get_running_loop().run_in_executor(
            self._pool, read_curve_isolated, name, text, part
        )
        # The token is held until the read ends, whether or not its client still waits.
        reading.add_done_callback(self._done)
        return await asyncio.shield(reading)

    def _done(self, reading: asyncio.Future[Curve]) -> None:
        if not reading.cancelled():
            reading.exception()  # seen, whoever is left to await it
        self.reading -= 1
        self.held -= 1
        self._tokens.release()


def low_priority_thread(name: str) -> ThreadPoolExecutor:
    """One thread, named `name`, at RETRIEVAL_NICENESS: retrievals and refinements run so,
    never in the thread pool that health checks, simulations and analyses use."""
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix=name, initializer=_lower_priority)


def _lower_priority() -> None:
    """This thread (and the threads it starts) at RETRIEVAL_NICENESS, if that is lower
    priority than it has; where threads have no niceness of their own, nothing."""
    try:
        thread = threading.get_native_id()
        if os.getpriority(os.PRIO_PROCESS, thread) < RETRIEVAL_NICENESS:
            os.setpriority(os.PRIO_PROCESS, thread, RETRIEVAL_NICENESS)
    except (AttributeError, OSError):  # not Linux
        pass
