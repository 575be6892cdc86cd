"""Where a generation shard's time goes: shards written in this process, its Python stack
sampled every millisecond of CPU time (a SIGPROF timer), each sample charged to the stage it
is in.

Python runs a signal's handler at the next bytecode, so a sample taken inside a compiled kernel
or a C call is charged to the Python function that made the call: kernels and Python are seen
alike, at the cost of a handler a millisecond (a profiler that hooks every call inflates the
Python stages several times over). Unix only, main thread only.
"""

from __future__ import annotations

import signal
import tempfile
import time
from collections import Counter
from dataclasses import replace
from types import FrameType

#: Stages by the function a sample is inside, innermost first: (stage, function names).
STAGES = (
    ("seeded generator of the topology", ("topology_rng",)),
    ("topology: J-operator growth and solution path", ("grow_topology",)),
    ("lock check of the negatives", ("lock_check",)),
    ("position search (compiled sampler and simulation)", ("search",)),
    ("transmission angles of the kept mechanisms", ("mechanism_transmission_deg",)),
    ("Arrow batches", ("batch",)),
    ("Parquet write and commit", ("write", "commit")),
)
OTHER = "other Python: row assembly, counters"


def _stage(frame: FrameType | None) -> str | None:
    """The stage of the innermost frame a stage names, or None outside `write_shard`."""
    names = []
    while frame is not None:
        names.append(frame.f_code.co_name)
        frame = frame.f_back
    if "write_shard" not in names:
        return None
    for name in names:
        for stage, functions in STAGES:
            if name in functions:
                return stage
    return OTHER


def profile_shard(topologies: int = 5200, seed: int = 0, interval_s: float = 0.001) -> dict:
    """Write one lean shard of `topologies` topologies (all 13 joint counts) into a temporary
    folder, sampling where its time goes; returns the seconds, the mechanisms a second and
    each stage's share of the samples."""
    from links_ray.data.generation import JOINT_COUNTS, GenerationPlan, write_shard
    from links_ray.data.store import Store

    per_size = max(1, topologies // JOINT_COUNTS)
    plan = GenerationPlan(
        seed=seed,
        mechanisms=5 * JOINT_COUNTS * per_size,
        tables=("mechanisms",),
        topologies_per_shard=per_size,
    )
    shards = plan.shards()
    warm = replace(shards[0], count=1)
    samples: Counter[str] = Counter()

    def sample(signum: int, frame: FrameType | None) -> None:
        stage = _stage(frame)
        if stage is not None:
            samples[stage] += 1

    with tempfile.TemporaryDirectory(prefix="links-profile-") as scratch:
        store = Store.open(f"{scratch}/warm")
        write_shard(store, plan, warm)  # loads the kernels' cache before the clock starts
        store = Store.open(f"{scratch}/root")
        mechanisms = 0
        previous = signal.signal(signal.SIGPROF, sample)
        start_cpu, start = time.process_time(), time.perf_counter()
        signal.setitimer(signal.ITIMER_PROF, interval_s, interval_s)
        try:
            for shard in shards:
                mechanisms += write_shard(store, plan, shard)["stats"]["mechanisms"]
        finally:
            signal.setitimer(signal.ITIMER_PROF, 0, 0)
            signal.signal(signal.SIGPROF, previous)
        seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - start_cpu
    total = sum(samples.values()) or 1
    return {
        "topologies": JOINT_COUNTS * per_size,
        "mechanisms": mechanisms,
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "mechanisms_per_second": mechanisms / seconds,
        "samples": total,
        "shares": {stage: samples[stage] / total for stage in [s for s, _ in STAGES] + [OTHER]},
    }
