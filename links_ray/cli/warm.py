"""Numba's compiled kernels: whether a command will compile them first, and compiling them
ahead of time (`links warm`, which the container image runs when it is built).

Every kernel is `cache=True`: the first run compiles it and saves the machine code beside its
module (`__pycache__`, or `NUMBA_CACHE_DIR`), and later runs load it. numba keys that code on
the module's path and modification time and on this machine's CPU, so a cache is cold after an
install, an edit, or on another CPU model.
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba.core.caching import NullCache
from numba.core.dispatcher import Dispatcher


@dataclass(frozen=True)
class KernelGroup:
    """Kernels a run compiles together, told by one of them (`anchor`): every run that uses
    the group compiles its anchor, so when the anchor's cache is cold the group's is."""

    name: str  # as the notice says it
    module: str
    anchor: str
    seconds: int  # about how long compiling the group takes on one core


SOLVER = KernelGroup("the solver's kernels", "links_ray.engine.solver", "_simulate_one", 15)
PATHS = KernelGroup("the path kernels", "links_ray.engine.paths", "_normalize_batch", 5)
SEARCH = KernelGroup("the search kernels", "links_ray.search.kernels", "_sketch_chamfer", 15)
REFINE = KernelGroup(
    "the refinement kernels", "links_ray.engine.refine_kernels", "_nearest_pairs", 5
)
#: Every group, as `links warm` checks them.
ALL_GROUPS = (SOLVER, PATHS, SEARCH, REFINE)

#: The groups each command compiles on its first run.
COMMAND_KERNELS: dict[str, tuple[KernelGroup, ...]] = {
    "demo": (SOLVER,),
    "generate": (SOLVER,),
    "curate": (PATHS,),
    "retrieve": (SEARCH, PATHS, SOLVER),
    "synthesize": (SEARCH, PATHS, SOLVER, REFINE),
    "serve": (SEARCH, PATHS, SOLVER),
}


#: Refinement iterations each warming synthesis runs: enough to reach every refinement kernel.
WARM_ITERATIONS = 20


def is_cached(dispatcher: Dispatcher) -> bool | None:
    """Whether numba's on-disk cache holds code of `dispatcher` that this process can load (its
    source unchanged, this CPU); None when the cache cannot be read (a numba this does not
    know: `pyproject.toml` bounds numba to the versions tested)."""
    cache = dispatcher._cache
    if isinstance(cache, NullCache):  # no cache (caching off): it compiles on every run
        return False
    try:
        # numba's own checks: the index is dropped when the source's stamp or numba's version
        # differ, and each entry's key names the CPU and the bytecode it was compiled for.
        index = cache._cache_file._load_index()
        codegen = dispatcher.targetctx.codegen()
        return any(key == cache._index_key(key[0], codegen) for key in index)
    except Exception:
        return None


def cold_groups(groups: tuple[KernelGroup, ...]) -> list[KernelGroup]:
    """The groups whose anchor has no loadable compiled code (unknown counts as warm)."""
    import importlib

    cold = []
    for group in groups:
        anchor = getattr(importlib.import_module(group.module), group.anchor)
        if is_cached(anchor) is False:
            cold.append(group)
    return cold


def compile_notice(command: str) -> str | None:
    """The line to print before `links COMMAND` compiles kernels, or None when their cache is
    warm (or the command compiles none)."""
    cold = cold_groups(COMMAND_KERNELS.get(command, ()))
    if not cold:
        return None
    names = " and ".join(group.name for group in cold)
    seconds = sum(group.seconds for group in cold)
    return f"links {command}: compiling {names} (first run only, about {seconds} s)..."


def note_compiling(command: str) -> None:
    """Say on stderr that this run compiles kernels, when it does."""
    notice = compile_notice(command)
    if notice:
        print(notice, file=sys.stderr, flush=True)


def warm(folder: str | None = None) -> dict[str, float]:
    """Compile every kernel into numba's cache by running, without Ray, what the commands run:
    generation shards (both samplers), their curation (from stored simulations and simulated
    again), a search index built on them, a retrieval and a synthesis (closed curve and open
    stroke). Works in `folder` (a temporary one by default) and returns the seconds of each
    stage."""
    if folder is None:
        with tempfile.TemporaryDirectory(prefix="links-warm-") as scratch:
            return warm(scratch)
    from links_ray.cli.demo import run_demo
    from links_ray.cluster.curation import ShardCurator
    from links_ray.data.lease import Lease
    from links_ray.data.schemas import CURATION_TABLES
    from links_ray.data.shards import GenerationPlan, write_shard
    from links_ray.data.store import Store
    from links_ray.engine.synthesis import synthesize
    from links_ray.search.index import RetrievalIndex

    seconds: dict[str, float] = {}
    start = time.perf_counter()
    run_demo(Path(folder) / "rejection", mechanisms=5, sampler="rejection")
    seconds["rejection sampler"] = time.perf_counter() - start

    start = time.perf_counter()
    store = Store.open(str(Path(folder) / "data"))
    # 260 mechanisms: four topologies of every joint count, enough curated paths for an index.
    plan = GenerationPlan(seed=0, mechanisms=260, topologies_per_shard=4)
    markers = [write_shard(store, plan, shard) for shard in plan.shards()]
    seconds["generation"] = time.perf_counter() - start

    start = time.perf_counter()
    with Lease.acquire(store, "writer", "links warm") as lease:
        curator = ShardCurator(store.uri, 0, lease.token, CURATION_TABLES, plan.steps)
        for number, marker in enumerate(markers):
            files = marker["files"]
            # One shard as curation does it for a root generated without simulations.
            stored = files["simulations"] if number else ""
            curator.curate(marker["shard"], marker["n_joints"], files["mechanisms"], stored)
    seconds["curation"] = time.perf_counter() - start

    start = time.perf_counter()
    index = RetrievalIndex.open(store)
    index.warm(seconds=0, queries=1)
    angle = np.linspace(0, 2 * np.pi, 60)
    curve = np.column_stack([np.cos(angle), 0.6 * np.sin(angle) + 0.2 * np.sin(2 * angle)])
    # A fixed amount of work, not a time budget: on a busy machine a budget can be spent
    # compiling before the refinement is reached, and its kernels left cold.
    synthesize(index, curve, k=2, iterations=WARM_ITERATIONS)
    synthesize(index, curve[:30], k=2, partial=True, iterations=WARM_ITERATIONS)
    seconds["search and synthesis"] = time.perf_counter() - start
    return seconds


def format_warm(seconds: dict[str, float]) -> str:
    """What `links warm` did, stage by stage."""
    from links_ray.cli import report

    cold = [group.name for group in cold_groups(ALL_GROUPS)]
    rows = [[stage, report.duration(s)] for stage, s in seconds.items()]
    return "\n".join(
        [
            report.table(["stage", "took"], rows),
            "kernels compiled and cached" if not cold else f"still cold: {', '.join(cold)}",
        ]
    )
