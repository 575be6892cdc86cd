"""Benchmarks of the services: `links bench generate` and `links bench retrieve`.

They run on a local Ray (started on demand) and write real datasets; the engine's benchmarks
are in `links_ray.cli.bench`.
"""

from __future__ import annotations

import json
import os
import shutil
import time

import numpy as np

from links_ray.cli.bench import machine_info
from links_ray.engine.mechanism import analyze_topology, arc_joints
from links_ray.engine.paths import is_circle, normalize_path
from links_ray.engine.sampling import PositionSampler
from links_ray.engine.solver import TopologySimulator
from links_ray.engine.topology import random_topology


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
                    "bytes_per_mechanism": _folder_bytes(f"{scratch}/{sampler}-{w}") / count,
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


def retrieval_dataset(paths: int, folder: str | None = None) -> str:
    """A cached dataset with at least `paths` curated paths (made once, then reused)."""
    from links_ray.cluster.curation import curate
    from links_ray.cluster.generation import generate

    root = folder or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")),
        "links-ray",
        f"retrieve-{paths}",
    )
    # About three curated paths per mechanism (measured); top up if a run falls short.
    mechanisms = max(1000, paths // 3)
    while True:
        generate(root, mechanisms, seed=2024, progress=False)
        summary = curate(root, progress=False)
        if summary["curated"] >= paths:
            return root
        shutil.rmtree(root)
        mechanisms = int(mechanisms * 1.2 * paths / max(summary["curated"], 1))


def bench_retrieve(paths: int = 1_000_000, queries: int = 1000, recall_queries: int = 100) -> dict:
    """Index build, latency in process and over HTTP, recall@3 against exact brute force.

    Queries are paths of mechanisms drawn afresh (held out of the dataset), neither arcs nor
    circles, given in a random frame: moved, turned, scaled and sometimes mirrored. Latency
    is timed on `queries` of them after the index's warm-up (`RetrievalIndex.warm`, which the
    Serve replica also runs before it takes traffic); recall on the first `recall_queries`.
    """
    import urllib.request

    from links_ray.search.index import RetrievalIndex

    root = retrieval_dataset(paths)
    start = time.perf_counter()
    index = RetrievalIndex.open(root, rebuild=True)
    build_s = time.perf_counter() - start
    start = time.perf_counter()
    RetrievalIndex.open(root)
    load_s = time.perf_counter() - start
    held_out = _held_out_queries(max(queries, recall_queries), seed=99)
    index.warm()
    in_process = []
    for query in held_out[:queries]:
        start = time.perf_counter()
        index.retrieve(query)
        in_process.append(time.perf_counter() - start)

    # Exact brute force for recall (the search is pruned but exact: see `brute_force`).
    truth = {
        number: {row for row, _, _ in index.brute_force(held_out[number])}
        for number in range(recall_queries)
    }
    hits = 0
    for number in range(recall_queries):
        normalized = normalize_path(held_out[number])
        hits += len({row for row, _, _ in index.ranked(normalized)} & truth[number])

    # Served as `links serve` serves: Ray started for it, the replica answering HTTP itself.
    import ray
    from ray import serve

    from links_ray.serve.app import bindable_port, run_server

    ray.shutdown()  # generating the dataset may have started one
    port = bindable_port("127.0.0.1", 0)
    run_server(root, port=port, blocking=False)
    over_http = []
    try:
        for query in [held_out[0], *held_out[:queries]]:
            body = json.dumps({"points": query.tolist(), "k": 3}).encode()
            request = urllib.request.Request(
                f"http://127.0.0.1:{port}/api/retrieve",
                data=body,
                headers={"Content-Type": "application/json"},
            )
            start = time.perf_counter()
            with urllib.request.urlopen(request, timeout=60) as response:
                response.read()
            over_http.append(time.perf_counter() - start)
    finally:
        serve.shutdown()
    over_http = over_http[1:]
    return {
        "benchmark": "retrieve",
        "machine": machine_info(),
        "paths": len(index),
        "build_s": build_s,
        "load_s": load_s,
        "index_bytes": index.nbytes,
        "p50_ms": float(np.percentile(over_http, 50) * 1e3),
        "p99_ms": float(np.percentile(over_http, 99) * 1e3),
        "in_process_p50_ms": float(np.percentile(in_process, 50) * 1e3),
        "in_process_p99_ms": float(np.percentile(in_process, 99) * 1e3),
        "max_ms": float(np.max(over_http) * 1e3),
        "in_process_max_ms": float(np.max(in_process) * 1e3),
        "recall_at_3": hits / (3 * recall_queries),
        "recall_queries": recall_queries,
        "queries": queries,
        "targets": {"p50_ms": 50, "p99_ms": 200, "recall_at_3": 0.95},
    }


def _held_out_queries(count: int, seed: int) -> list[np.ndarray]:
    """Paths of fresh random mechanisms in random frames (not arcs, not circles)."""
    rng = np.random.default_rng(seed)
    queries = []
    while len(queries) < count:
        adjacency, node_types = random_topology(rng)
        simulator = TopologySimulator(adjacency, node_types)
        found = PositionSampler(simulator).search(1, rng, "sequential")
        arcs = arc_joints(analyze_topology(adjacency, node_types))
        joint = int(rng.choice(np.flatnonzero((node_types != 0) & ~arcs)))
        path = found.trajectories[0, joint]
        if is_circle(normalize_path(path)):
            continue
        angle = rng.uniform(0, 2 * np.pi)
        turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        if rng.random() < 0.5:
            turn = turn @ np.diag([1.0, -1.0])
        queries.append(path @ turn.T * rng.uniform(0.5, 20) + rng.uniform(-10, 10, 2))
    return queries


def format_retrieve(result: dict) -> str:
    """Retrieval latency, recall and memory beside the targets."""
    return "\n".join(
        [
            f"{result['paths']:,} curated paths; index built in {result['build_s']:.1f} s, "
            f"loaded in {result['load_s']:.1f} s, {result['index_bytes'] / 1e9:.2f} GB in memory",
            f"over HTTP: p50 {result['p50_ms']:.1f} ms, p99 {result['p99_ms']:.1f} ms, "
            f"slowest {result['max_ms']:.0f} ms of {result['queries']} (targets 50 / 200 ms)",
            f"in process: p50 {result['in_process_p50_ms']:.1f} ms, "
            f"p99 {result['in_process_p99_ms']:.1f} ms, "
            f"slowest {result['in_process_max_ms']:.0f} ms",
            f"recall@3 against exact brute force: {result['recall_at_3']:.3f} on "
            f"{result['recall_queries']} held-out queries (target 0.95)",
        ]
    )


def _folder_bytes(folder: str) -> int:
    return sum(
        os.path.getsize(os.path.join(root, name))
        for root, _, names in os.walk(folder)
        for name in names
    )


def format_generate(result: dict) -> str:
    """Generation throughput by sampler and worker count."""
    lines = [
        f"{'sampler':<12}{'workers':>8}{'mechanisms':>12}{'seconds':>10}"
        f"{'per second':>12}{'per core-s':>12}{'in actor':>10}{'bytes/mech':>12}"
    ]
    for run in result["runs"]:
        lines.append(
            f"{run['sampler']:<12}{run['workers']:>8}{run['mechanisms']:>12,}"
            f"{run['seconds']:>10.2f}{run['mechanisms_per_second']:>12,.0f}"
            f"{run['valid_per_core_second']:>12,.0f}"
            f"{run['in_actor_valid_per_core_second']:>10,.0f}{run['bytes_per_mechanism']:>12,.0f}"
        )
    lines.append(
        f"End to end with all workers: {result['valid_per_core_second']:,.0f} valid mechanisms "
        f"per core-second (target {result['target_valid_per_core_second']:,})"
    )
    return "\n".join(lines)
