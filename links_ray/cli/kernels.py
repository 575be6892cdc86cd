"""Numba's compiled kernels: which groups a command compiles on its first run, and whether
they are cached, for the notice a command prints before it compiles (`links warm` compiles
them all ahead of time).

Every kernel is `cache=True`: the first run compiles it and saves the machine code beside its
module (`__pycache__`, or `NUMBA_CACHE_DIR`), and later runs load it. numba keys that code on
the module's path and modification time and on this machine's CPU, so a cache is cold after an
install, an edit, or on another CPU model.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

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


SOLVER = KernelGroup(
    "the solver's kernels", "links_ray.engine.kinematics.solver", "_simulate_one", 15
)
PATHS = KernelGroup("the path kernels", "links_ray.engine.kinematics.paths", "_normalize_batch", 5)
SEARCH = KernelGroup("the search kernels", "links_ray.search.kernels", "_sketch_chamfer", 15)
REFINE = KernelGroup(
    "the refinement kernels", "links_ray.engine.synthesis.refinement.kernels", "_nearest_pairs", 5
)
# Its own group: an edit of `step_kernels` alone leaves `refine_kernels`' cache warm.
STEP = KernelGroup(
    "the refinement step's kernels",
    "links_ray.engine.synthesis.refinement.step_kernels",
    "_chamfer_system",
    5,
)
#: Every group, as `links warm` checks them.
ALL_GROUPS = (SOLVER, PATHS, SEARCH, REFINE, STEP)

#: The groups each command compiles on its first run.
COMMAND_KERNELS: dict[str, tuple[KernelGroup, ...]] = {
    "demo": (SOLVER,),
    "generate": (SOLVER,),
    "curate": (PATHS,),
    "retrieve": (SEARCH, PATHS, SOLVER),
    "synthesize": (SEARCH, PATHS, SOLVER, REFINE, STEP),
    "serve": (SEARCH, PATHS, SOLVER),
}


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
