"""`links warm`: every kernel compiled into numba's cache ahead of time, which the container
image runs when it is built (`links_ray.cli.kernels` says which groups each command compiles).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from links_ray.cli import report
from links_ray.cli.arguments import json_option, print_result
from links_ray.cli.kernels import ALL_GROUPS, cold_groups


def add_command(commands: argparse._SubParsersAction) -> None:
    """Register `links warm` on the `links` command's subparsers."""
    command = commands.add_parser(
        "warm",
        help="compile every kernel into numba's cache now (the container image does this)",
    )
    command.add_argument(
        "--folder", default=None, help="work folder (default: a temporary one, removed after)"
    )
    json_option(command, "each stage's seconds")
    command.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links warm`: compile, then print each stage's seconds."""
    print_result(args, warm(args.folder), format_warm)


#: Refinement iterations each warming synthesis runs: enough to reach every refinement kernel.
WARM_ITERATIONS = 20


def warm(folder: str | None = None) -> dict[str, float]:
    """Compile every kernel into numba's cache by running, without Ray, what the commands run:
    generation shards (both samplers), their curation (from stored simulations and simulated
    again), a search index built on them, a retrieval and a synthesis (closed curve, open
    stroke, Pareto front). Works in `folder` (a temporary one by default) and returns the
    seconds of each stage."""
    if folder is None:
        with tempfile.TemporaryDirectory(prefix="links-warm-") as scratch:
            return warm(scratch)
    from links_ray.cli.demo import run_demo
    from links_ray.cluster.curation import ShardCurator
    from links_ray.data.generation import GenerationPlan, write_shard
    from links_ray.data.lease import Lease
    from links_ray.data.schemas import CURATION_TABLES
    from links_ray.data.store import Store
    from links_ray.engine.synthesis.pipeline import synthesize
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
    # A counted amount of work, not a time budget: on a busy machine a budget can be spent
    # compiling before the refinement is reached, and its kernels left cold.
    synthesize(index, curve, k=2, iterations=WARM_ITERATIONS)
    synthesize(index, curve[:30], k=2, partial=True, iterations=WARM_ITERATIONS)
    # A front plans layers: the collision kernels (timing and constraints call no others).
    synthesize(index, curve, k=2, front=True, iterations=WARM_ITERATIONS)
    seconds["search and synthesis"] = time.perf_counter() - start
    return seconds


def format_warm(seconds: dict[str, float]) -> str:
    """What `links warm` did, stage by stage."""
    cold = [group.name for group in cold_groups(ALL_GROUPS)]
    rows = [[stage, report.duration(s)] for stage, s in seconds.items()]
    return "\n".join(
        [
            report.table(["stage", "took"], rows),
            "kernels compiled and cached" if not cold else f"still cold: {', '.join(cold)}",
        ]
    )
