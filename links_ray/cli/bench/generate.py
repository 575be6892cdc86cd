"""`links bench generate`: end-to-end generation throughput on a local Ray, by worker count and
sampler."""

from __future__ import annotations

import os
import time

from links_ray.cli import report
from links_ray.cli.bench.data import folder_bytes
from links_ray.cli.bench.machine import machine_info


def bench_generate(
    mechanisms: int = 50_000,
    rejection_mechanisms: int = 2_000,
    workers: list[int] | None = None,
    topologies_per_shard: int = 100,
) -> dict:
    """End-to-end generation on the local Ray: valid mechanisms per core-second, by workers.

    Each run writes a fresh dataset (rules, five variants, 200-step simulations, negatives,
    Parquet) into a temporary folder. Wall-clock time covers the whole `generate` call with Ray
    already started: new actors loading the compiled kernels, scheduling, commits.
    """
    import tempfile

    from links_ray.cluster.connect import connect
    from links_ray.cluster.generation import generate

    connect()
    cpus = os.cpu_count() or 1
    counts = workers or sorted({1, cpus})
    runs = []
    with tempfile.TemporaryDirectory(prefix="links-bench-") as scratch:
        # Warm the actors' kernel cache so no run pays for compilation.
        generate(f"{scratch}/warm", 65, workers=max(counts), progress=False)
        cases = [("sequential", mechanisms, w) for w in counts]
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
    return {
        "benchmark": "generate",
        "machine": machine_info(),
        "runs": runs,
        "valid_per_core_second": sequential[-1]["valid_per_core_second"],
        "rejection_valid_per_core_second": runs[-1]["valid_per_core_second"],
        "target_valid_per_core_second": 1000,
    }


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
    return "\n".join(
        [
            report.table(header, rows),
            f"End to end with all workers: {result['valid_per_core_second']:,.0f} valid "
            f"mechanisms per core-second (target {result['target_valid_per_core_second']:,})",
        ]
    )
