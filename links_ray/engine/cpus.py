"""How many threads this process may keep busy: the one answer synthesis and retrieval use.

A process is given CPUs by whatever runs it. On Linux its affinity mask says which cores it may
run on (a container's cpuset, `taskset`); `os.cpu_count()` counts the machine's cores whatever
the process was given, so sizing a pool by it oversubscribes a process pinned to fewer.
Under a scheduler that hands out CPUs as a number (a Ray Serve replica's `num_cpus`), the
process runs where it likes but is meant to use that many; the layer that knows it (the Serve
app, which may import Ray) says so once with `set_given_cpus`, and `usable_cpus` keeps to it.

Pure Python: no Ray.
"""

from __future__ import annotations

import math
import os

__all__ = ["given_cpus", "set_given_cpus", "usable_cpus"]

#: The CPUs a scheduler gave this process, if one said (`set_given_cpus`).
_given: float | None = None


def set_given_cpus(cpus: float | None) -> None:
    """Record the CPUs a scheduler gave this process (fractions allowed), or forget them with
    None. Raises ValueError for a negative or non-finite count."""
    global _given
    if cpus is not None:
        if isinstance(cpus, bool) or not isinstance(cpus, int | float):
            raise ValueError(f"cpus must be a number, got {cpus!r}")
        if not math.isfinite(cpus) or cpus < 0:
            raise ValueError(f"cpus must be a finite number >= 0, got {cpus!r}")
        cpus = float(cpus)
    _given = cpus


def given_cpus() -> float | None:
    """The CPUs a scheduler gave this process, as `set_given_cpus` recorded them, or None."""
    return _given


def _affinity() -> int:
    """Cores this process may run on: its affinity mask where the platform has one."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)  # no affinity masks here (macOS): every core


def usable_cpus() -> int:
    """Threads worth running at once in this process: the CPUs a scheduler gave it, whole
    ones (at least 1), within the cores its affinity allows; else the cores its affinity
    allows."""
    cores = _affinity()
    if _given is None:
        return cores
    return max(1, min(cores, math.floor(_given + 1e-9)))
