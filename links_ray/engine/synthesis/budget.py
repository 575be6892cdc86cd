"""How much work a synthesis may do: a time (`TimeBudget`) or a count of refinement
iterations (`IterationBudget`, whose answers are bit-equal whatever the time, the load and the
threads). The passes (`engine.synthesis.passes`) run one loop and ask the budget when a pass
is done, what deadline a refinement gets, and whether rounds run in lockstep. Either may be
called off (`stop`, set when a synthesis's client has gone): every pass is then done, and a
refinement under way ends at its next iteration.

Pure Python: no Ray.
"""

from __future__ import annotations

import math
import threading
import time
from abc import ABC, abstractmethod

from links_ray.engine.synthesis.refinement.loop import Refinement

__all__ = ["Budget", "IterationBudget", "TimeBudget"]


class Budget(ABC):
    """The work a synthesis may do, and the refinement iterations it has spent so far; `stop`,
    once set, calls the rest off (a new Event if None)."""

    #: Whether each round of refinement waits for all its candidates before the next starts:
    #: then every candidate gets the same work whatever the threads (`IterationBudget`).
    lockstep: bool
    #: When the work must end, by `time.perf_counter()` (inf when it ends by a count).
    deadline: float

    def __init__(self, stop: threading.Event | None = None) -> None:
        self.spent = 0  # refinement iterations so far (each attempt counts one at least)
        self._counting = threading.Lock()  # workers add to `spent` at once
        self.stop = threading.Event() if stop is None else stop

    def stopped(self) -> bool:
        """Whether the work has been called off (`stop` is set)."""
        return self.stop.is_set()

    def charge(self, refinement: Refinement | None) -> Refinement | None:
        """Count `refinement`'s iterations (one for an attempt that did none), and return it."""
        with self._counting:
            self.spent += max(1, refinement.iterations if refinement is not None else 0)
        return refinement

    @abstractmethod
    def pass_end(self, share: float) -> float:
        """When a pass given `share` of what is left must end (`time.perf_counter()`)."""

    @abstractmethod
    def share_end(self, share: float) -> float:
        """When `share` of the whole budget is spent (`time.perf_counter()`): the end of a pass
        that may run until then, which `done(share, end)` tells."""

    @abstractmethod
    def done(self, share: float, end: float) -> bool:
        """Whether a pass that may take `share` of the work, or run until `end`, is done (at once
        when called off)."""

    @abstractmethod
    def refine_deadline(self, end: float) -> float | None:
        """The deadline one refinement of a pass ending at `end` is given (None: none)."""

    @abstractmethod
    def expired(self) -> bool:
        """Whether the whole budget is spent (or called off), for work that is skipped past it."""

    @abstractmethod
    def at_once(self, workers: int, steady: int) -> int:
        """How many candidates a round refines together: `workers`, or `steady` whatever the
        threads."""

    @abstractmethod
    def left(self) -> float:
        """The share of the whole budget not yet spent (0 to 1)."""


class TimeBudget(Budget):
    """`seconds` of work from `started` (a `time.perf_counter()` value), unless `stop` is set
    first."""

    lockstep = False

    def __init__(self, started: float, seconds: float, stop: threading.Event | None = None) -> None:
        super().__init__(stop)
        self.deadline = started + seconds
        self.seconds = seconds

    def pass_end(self, share: float) -> float:
        """Now, plus `share` of the time left."""
        now = time.perf_counter()
        return now + share * max(0.0, self.deadline - now)

    def share_end(self, share: float) -> float:
        """The deadline, less the rest of the seconds."""
        return self.deadline - (1.0 - share) * self.seconds

    def done(self, share: float, end: float) -> bool:
        """Whether `end` has passed, or the work is called off."""
        return self.stopped() or time.perf_counter() >= end

    def refine_deadline(self, end: float) -> float | None:
        """`end` itself."""
        return end

    def expired(self) -> bool:
        """Whether the deadline has passed, or the work is called off."""
        return self.stopped() or time.perf_counter() > self.deadline

    def at_once(self, workers: int, steady: int) -> int:
        """`workers`: a core for each."""
        return workers

    def left(self) -> float:
        """The share of the seconds still to come."""
        return min(1.0, max(0.0, self.deadline - time.perf_counter()) / max(self.seconds, 1e-9))


class IterationBudget(Budget):
    """About `iterations` refinement iterations over all candidates, checked between rounds:
    no deadline, so the answer depends on nothing but the inputs (unless `stop` is set)."""

    lockstep = True
    deadline = math.inf

    def __init__(self, iterations: int, stop: threading.Event | None = None) -> None:
        super().__init__(stop)
        self.iterations = iterations

    def pass_end(self, share: float) -> float:
        """Never: a counted pass ends by its count."""
        return math.inf

    def share_end(self, share: float) -> float:
        """Never: a counted pass ends by its count."""
        return math.inf

    def done(self, share: float, end: float) -> bool:
        """Whether `share` of the iterations are spent, or the work is called off."""
        return self.stopped() or self.spent >= share * self.iterations

    def refine_deadline(self, end: float) -> float | None:
        """None: a refinement stops by its iterations alone."""
        return None

    def expired(self) -> bool:
        """Only once called off: counted work has no deadline."""
        return self.stopped()

    def at_once(self, workers: int, steady: int) -> int:
        """`steady`, whatever the threads."""
        return steady

    def left(self) -> float:
        """The share of the iterations not yet spent."""
        return max(0.0, 1.0 - self.spent / self.iterations)
