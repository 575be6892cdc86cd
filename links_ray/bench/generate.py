"""`links bench generate`: end-to-end generation throughput on a local Ray, by worker count and
sampler."""

from __future__ import annotations

import os
import time

from links_ray.bench.data import folder_bytes
from links_ray.bench.machine import machine_info
from links_ray.cli import report
from links_ray.data.generation import TOPOLOGIES_PER_SHARD
from links_ray.data.schemas import GENERATION_TABLES

#: Valid mechanisms a core-second: of a run writing every table, and of a lean run (the
#: `mechanisms` table alone), whose rate makes 100 million a run of under two hours here.
TARGET_VALID_PER_CORE_SECOND = 1000
LEAN_TARGET_VALID_PER_CORE_SECOND = 8000


def bench_generate(
    mechanisms: int = 50_000,
    rejection_mechanisms: int = 2_000,
    workers: list[int] | None = None,
    topologies_per_shard: int | None = None,
    lean: bool = False,
) -> dict:
    """End-to-end generation on the local Ray: valid mechanisms per core-second, by workers.

    Each run writes a fresh dataset (rules, five variants, Parquet; with every table, also the
    200-step simulations and negatives) into a temporary folder. Wall-clock time covers the
    whole `generate` call with Ray already started: new actors loading the compiled kernels,
    scheduling, commits. `lean` writes the `mechanisms` table alone, with the sequential
    sampler only, and adds where one shard's time goes (`shard_profile`). Shards hold
    `topologies_per_shard` topologies: by default 100 (many shards, so that short runs keep
    every worker busy), and for a lean run the default of `links generate`, as a long lean run
    has them.
    """
    import tempfile

    from links_ray.bench.shard_profile import profile_shard
    from links_ray.cluster.connect import connect
    from links_ray.cluster.generation import generate

    tables = ("mechanisms",) if lean else GENERATION_TABLES
    if topologies_per_shard is None:
        topologies_per_shard = TOPOLOGIES_PER_SHARD if lean else 100
    profile = profile_shard() if lean else None  # before Ray takes the cores
    connect()
    cpus = os.cpu_count() or 1
    counts = workers or sorted({1, cpus})
    runs = []
    with tempfile.TemporaryDirectory(prefix="links-bench-") as scratch:
        # Warm the actors' kernel cache so no run pays for compilation.
        generate(f"{scratch}/warm", 65, workers=max(counts), progress=False, tables=tables)
        cases = [("sequential", mechanisms, w) for w in counts]
        if not lean:
            cases.append(("rejection", rejection_mechanisms, max(counts)))
        for sampler, count, w in cases:
            start = time.perf_counter()
            summary = generate(
                f"{scratch}/{sampler}-{w}",
                count,
                workers=w,
                sampler=sampler,
                progress=False,
                topologies_per_shard=topologies_per_shard,
                tables=tables,
            )
            seconds = time.perf_counter() - start
            runs.append(
                {
                    "sampler": sampler,
                    "workers": w,
                    "mechanisms": count,
                    "seconds": seconds,
                    "mechanisms_per_second": count / seconds,
                    "valid_per_core_second": count / seconds / w,
                    # Time inside the actors only: no Ray start-up, scheduling or commits.
                    "in_actor_valid_per_core_second": summary["valid_per_core_second"],
                    "bytes_per_mechanism": folder_bytes(f"{scratch}/{sampler}-{w}") / count,
                }
            )
    sequential = [run for run in runs if run["sampler"] == "sequential"]
    result = {
        "benchmark": "generate",
        "machine": machine_info(),
        "tables": list(tables),
        "runs": runs,
        "valid_per_core_second": sequential[-1]["valid_per_core_second"],
        "target_valid_per_core_second": (
            LEAN_TARGET_VALID_PER_CORE_SECOND if lean else TARGET_VALID_PER_CORE_SECOND
        ),
    }
    if lean:
        result["profile"] = profile
    else:
        result["rejection_valid_per_core_second"] = runs[-1]["valid_per_core_second"]
    return result


def format_generate(result: dict) -> str:
    """Generation throughput by sampler and worker count."""
    header = ["sampler", "workers", "mechanisms", "seconds", "per second", "per core-s"]
    header += ["in actor", "bytes/mech"]
    rows = [
        [
            run["sampler"],
            run["workers"],
            report.count(run["mechanisms"]),
            f"{run['seconds']:.2f}",
            f"{run['mechanisms_per_second']:,.0f}",
            f"{run['valid_per_core_second']:,.0f}",
            f"{run['in_actor_valid_per_core_second']:,.0f}",
            f"{run['bytes_per_mechanism']:,.0f}",
        ]
        for run in result["runs"]
    ]
    lines = [
        f"Tables written: {', '.join(result['tables'])}",
        report.table(header, rows),
        f"End to end with all workers: {result['valid_per_core_second']:,.0f} valid "
        f"mechanisms per core-second (target {result['target_valid_per_core_second']:,})",
    ]
    profile = result.get("profile")
    if profile:
        lines += [
            "",
            f"Where one lean shard's time goes ({profile['topologies']:,} topologies, "
            f"{profile['mechanisms']:,} mechanisms, in this process: "
            f"{profile['mechanisms_per_second']:,.0f} a second; {profile['samples']:,} "
            "samples of its stack):",
            report.table(
                ["stage", "share"],
                [[stage, f"{share:.1%}"] for stage, share in profile["shares"].items()],
            ),
        ]
    return "\n".join(lines)
