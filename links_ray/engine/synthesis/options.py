"""One synthesis request's options, validated once where the request enters (the Python
`synthesize`, the CLI's `links synthesize`, HTTP's `/api/synthesize`), and the limits they
keep. The passes (`engine.synthesis.passes`) take a `SynthesisOptions` and check nothing again.

Pure numpy: no numba, no Ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from links_ray.engine.inputs import (
    DEFAULT_K,
    MAX_K,
    MAX_POINTS,
    MIN_K,
    as_drawn_points,
    as_flag,
    as_int,
    as_max_joints,
    as_real_array,
    as_transmission_deg,
    positive_at_most,
    shown,
)
from links_ray.engine.synthesis.constraints import Constraints, as_constraints
from links_ray.engine.synthesis.plan import retrievals

__all__ = [
    "DEFAULT_SYNTHESIS_SECONDS",
    "DEFAULT_SYNTHESIS_TRANSMISSION_DEG",
    "MAX_SEED",
    "MAX_SYNTHESIS_ITERATIONS",
    "MAX_SYNTHESIS_SECONDS",
    "MAX_SYNTHESIS_WORK",
    "MAX_TIMING_DEG",
    "SynthesisOptions",
    "as_seconds",
    "as_timing",
]

#: The least transmission angle, in degrees, a synthesis keeps unless asked for another: a
#: mechanism a builder can turn by hand without it jamming at a dead centre, chosen by what it
#: costs in fit on the bench (docs/benchmarks.md, A floor a builder can trust). 0 relaxes it
#: to refinement's own margin (DEFAULT_MIN_TRANSMISSION_DEG, on dyads that have it).
DEFAULT_SYNTHESIS_TRANSMISSION_DEG = 10.0
#: Seconds a synthesis takes by default (retrieval included), and the most it may be given:
#: a synthesis holds a core for its whole budget, so a request may not hold one for long.
DEFAULT_SYNTHESIS_SECONDS, MAX_SYNTHESIS_SECONDS = 3.0, 30.0
#: Most refinement iterations a synthesis of counted work may be given (`iterations`, summed over
#: its candidates): about what MAX_SYNTHESIS_SECONDS allow on two cores (docs/benchmarks.md,
#: Synthesis), so that counted work holds a replica about as long as a timed one.
MAX_SYNTHESIS_ITERATIONS = 10_000
#: Most counted work a synthesis may be given, in point-iterations: the drawing's points times
#: its refinement iterations, `iterations` and CANDIDATE_ITERATIONS for each candidate it
#: retrieves (`counted_work_units`). An iteration pairs every drawn point with the path (and
#: a stroke searches for its best run along it), so its cost grows with the points; the
#: iterations alone would let a 10,000-point stroke hold the refiner for minutes. Sized so
#: that the costliest request within it (a Pareto front of the longest stroke it allows)
#: answers within a minute on two cores, and every request of the tests and benches is within.
MAX_SYNTHESIS_WORK = 15_000_000
#: Iterations each retrieved candidate costs whatever `iterations` says: its preparation, and
#: the short pass's first round (`synthesis_passes.FIRST_ROUND`), which every candidate gets.
CANDIDATE_ITERATIONS = 10
#: The most a `timing` angle may be, either way, in degrees: thousands of turns.
MAX_TIMING_DEG = 1e6
#: Seeds are what numpy's generators take whole: non-negative, here within 64 bits.
MAX_SEED = 2**64 - 1


def as_seconds(value: object) -> float:
    """A synthesis time budget in seconds: more than 0 and at most MAX_SYNTHESIS_SECONDS;
    None gives DEFAULT_SYNTHESIS_SECONDS."""
    if value is None:
        return DEFAULT_SYNTHESIS_SECONDS
    return positive_at_most(value, "seconds", MAX_SYNTHESIS_SECONDS, "a number", "")


def as_timing(timing: object, count: int, partial: bool) -> np.ndarray | None:
    """Crank angles in radians (count,) at which the drawn points are to be reached, relative
    to the first: `True` is equal steps of a whole turn, a list gives them in degrees; None or
    False is no timing. Raises ValueError naming the problem."""
    if timing is None or timing is False:
        return None
    if timing is True:
        if partial:
            raise ValueError(
                "timing=true spreads the points over a whole turn, which a partial stroke "
                "does not make: give the stroke's crank angles as a list"
            )
        return 2.0 * np.pi * np.arange(count) / count
    if isinstance(timing, str | bytes | dict) or not hasattr(timing, "__len__"):
        raise ValueError(f"timing must be true or a list of angles in degrees, got {shown(timing)}")
    if isinstance(timing, list | tuple) and len(timing) != count:  # before any angle is read
        raise ValueError(f"timing must give one angle per point: {count}, got {len(timing)}")
    if any(isinstance(v, bool) for v in timing):  # type: ignore[union-attr]
        raise ValueError("timing must be true or a list of angles in degrees")
    degrees = as_real_array("timing", timing, "true or a list of angles in degrees")
    if degrees.ndim != 1 or len(degrees) != count:
        raise ValueError(f"timing must give one angle per point: {count}, got {degrees.size}")
    if not np.all(np.isfinite(degrees)) or np.any(np.abs(degrees) > MAX_TIMING_DEG):
        raise ValueError(f"timing must be finite angles in degrees within +-{MAX_TIMING_DEG:g}")
    return np.radians(degrees - degrees[0])


#: What `timing` may be once checked: True (equal steps of a turn), the crank angle of each
#: point in degrees, or None (no timing).
Timing = bool | tuple[float, ...] | None


@dataclass(frozen=True)
class SynthesisOptions:
    """What a synthesis is asked for, checked when made (ValueError naming a bad field, by its
    public name): the HTTP body's and `synthesize`'s arguments but the points.

    `k` results (a `front` instead gives the best of each joint count that beats every simpler
    one). The work: `seconds` of time (None given: DEFAULT_SYNTHESIS_SECONDS), or with
    `iterations` about that many refinement iterations, `seconds` then None (`counted_work`);
    `seed` seeds the restarts (None given: 0). `partial`: the points are an open stroke.
    `min_transmission_deg` (HTTP and `synthesize`: `min_transmission`): the transmission floor
    of what is retrieved and of what refinement keeps (default
    DEFAULT_SYNTHESIS_TRANSMISSION_DEG). `max_joints`, `constraints` and
    `timing` (True, or one angle in degrees a point; `timing_angles` checks their count) are
    the design's.
    """

    k: int = DEFAULT_K
    seconds: float | None = None
    partial: bool = False
    min_transmission_deg: float = DEFAULT_SYNTHESIS_TRANSMISSION_DEG
    max_joints: int | None = None
    front: bool = False
    constraints: Constraints | None = None
    timing: Timing = None
    seed: int = 0
    iterations: int | None = None

    def __post_init__(self) -> None:
        # In the order the checks always ran, so a request with several faults is told the same.
        seed = 0 if self.seed is None else as_int("seed", self.seed, 0, MAX_SEED)
        iterations = self.iterations
        if iterations is None:
            seconds: float | None = as_seconds(self.seconds)
        else:
            iterations = as_int("iterations", iterations, 1, MAX_SYNTHESIS_ITERATIONS)
            if self.seconds is not None:
                raise ValueError(
                    "give seconds or iterations, not both: iterations fix the work whatever "
                    "the time"
                )
            seconds = None
        checked = {
            "seed": seed,
            "iterations": iterations,
            "seconds": seconds,
            "k": as_int("k", self.k, MIN_K, MAX_K),
            "partial": as_flag(self.partial, "partial"),
            "min_transmission_deg": as_transmission_deg(
                self.min_transmission_deg, "min_transmission"
            ),
            "max_joints": as_max_joints(self.max_joints),
            "front": as_flag(self.front, "front"),
            "constraints": as_constraints(self.constraints),
            "timing": _as_timing_given(self.timing, as_flag(self.partial, "partial")),
        }
        for name, value in checked.items():
            object.__setattr__(self, name, value)  # frozen: set once, here

    @property
    def counted_work(self) -> bool:
        """Whether the work is a number of iterations (bit-equal answers), not a time."""
        return self.iterations is not None

    def drawing(self, points: object) -> np.ndarray:
        """The drawn `points` as a float64 (T, 2) array, checked with the options that depend
        on them (one timing angle a point, counted work within MAX_SYNTHESIS_WORK), or
        ValueError naming the problem."""
        drawn = as_drawn_points(points)
        self.timing_angles(len(drawn))
        self.check_work(len(drawn))
        return drawn

    def counted_work_units(self, count: int) -> int | None:
        """The point-iterations counted work on `count` points asks for (`count` times
        `iterations` and CANDIDATE_ITERATIONS a candidate retrieved), None for timed work."""
        if self.iterations is None:
            return None
        wanted = retrievals(self.k, self.max_joints, self.front, self.min_transmission_deg)
        candidates = sum(asked for asked, _, _ in wanted)
        return count * (self.iterations + CANDIDATE_ITERATIONS * candidates)

    def check_work(self, count: int) -> None:
        """ValueError naming MAX_SYNTHESIS_WORK and the request's units if counted work on
        `count` points would pass it."""
        units = self.counted_work_units(count)
        if units is None or units <= MAX_SYNTHESIS_WORK:
            return
        candidates = units // count - self.iterations  # type: ignore[operator]
        most = MAX_SYNTHESIS_WORK // count - candidates
        fewer = (
            f"at most {most} iterations for {count} points"
            if most >= 1
            else f"at most {MAX_SYNTHESIS_WORK // (self.iterations + candidates)} points"  # type: ignore[operator]
        )
        raise ValueError(
            f"counted work must be at most {MAX_SYNTHESIS_WORK:,} point-iterations "
            f"(MAX_SYNTHESIS_WORK), got {count} points x ({self.iterations} iterations + "
            f"{candidates} for the candidates) = {units:,}: give {fewer}, or seconds"
        )

    def timing_angles(self, count: int) -> np.ndarray | None:
        """The crank angles in radians (count,) at which `count` points are to be reached
        (`as_timing`), or None without timing."""
        return as_timing(self.timing, count, self.partial)


def _as_timing_given(timing: object, partial: bool) -> Timing:
    """`timing` as a `SynthesisOptions` keeps it: None for none, True, or a tuple of the angles
    given, refused here if no count of points could make it right (`as_timing`, given the
    points' count by `SynthesisOptions.drawing`, checks the rest)."""
    if timing is None or timing is False:
        return None
    if timing is True:
        as_timing(True, 1, partial)
        return True
    if isinstance(timing, str | bytes | dict) or not hasattr(timing, "__len__"):
        raise ValueError(f"timing must be true or a list of angles in degrees, got {shown(timing)}")
    angles = len(timing)  # type: ignore[arg-type]
    if angles > MAX_POINTS:  # before any angle is read
        raise ValueError(
            f"timing must give one angle per point, at most {MAX_POINTS}, got {angles}"
        )
    return tuple(timing)  # type: ignore[call-overload]
