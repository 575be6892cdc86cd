"""`links bench serve`: the app under load. Clients retrieve while another checks health and
simulates, with one index in the front and with the index split into shards; then clients post
the largest bodies the limits allow while another checks health."""

from __future__ import annotations

import contextlib
import json
import os
import urllib.request
from collections.abc import Iterator
from typing import Any

import numpy as np

from links_ray.bench.data import retrieval_dataset
from links_ray.bench.held_out import held_out_queries
from links_ray.bench.load_clients import (
    finish_load,
    health_probes,
    largest_simulation,
    post_load,
    probe_loop,
    retrieval_load,
    wait_for_port,
)
from links_ray.bench.machine import machine_info
from links_ray.cli import report

#: Clients posting the largest bodies at once, in the last run.
LARGEST_BODY_CLIENTS = 8
#: What health checks should stay under while they do (99th percentile, milliseconds): the
#: event loop that answers health parses no body and renders no answer of theirs.
LARGEST_BODY_HEALTH_P99_TARGET_MS = 100.0


def _ms(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q) * 1e3) if values else None


def bench_serve(
    shards: list[int] | None = None,
    seconds: float = 30.0,
    clients: int = 32,
    paths: int = 60_000,
    root: str | None = None,
    largest_bodies: bool = True,
) -> dict:
    """Serving under load: `clients` clients retrieving for `seconds` while another checks
    health and simulates, for each count in `shards` (0: one index in the front). The app is
    served as `links serve` serves it, on a Ray started for the benchmark (one for all the
    runs), the front answering HTTP itself.

    Reports retrievals answered per second, p50/p99 of the answered retrievals and of the
    health checks and simulations, and the 503s. Shard replicas get an equal share of the
    CPUs the front leaves (at most one each). The clients run on the same machine as the
    server. With `largest_bodies`, a last run posts the largest simulations the limits allow
    and reports health meanwhile against LARGEST_BODY_HEALTH_P99_TARGET_MS.
    """
    import ray

    from links_ray.cluster.connect import connect
    from links_ray.search.index import RetrievalIndex
    from links_ray.serve.app import (
        build_app,
        check_root,
        direct_ingress_env,
        fit_partition_cpus,
    )

    counts = [0, 1, 2] if shards is None else shards
    root = root or retrieval_dataset(paths)
    for count in counts:
        check_root(root, count or None)
    queries = held_out_queries(64, seed=77)
    ray.shutdown()  # generating the dataset may have started one
    port = _listening_port()
    os.environ.update(direct_ingress_env(port))
    connect()
    no_access_log = {"enable_access_log": False}
    runs = []
    try:
        for count in counts:
            parts = max(count, 1)
            for part in range(parts):  # built before the run, not during it
                RetrievalIndex.open(root, part=part, parts=parts)
            shard_cpus = fit_partition_cpus(1, count, ray.cluster_resources()) if count else None
            app = build_app(root, shards=count or None, shard_cpus=shard_cpus or 1.0)
            with _served(app, port, no_access_log):
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health") as response:
                    indexed = json.loads(response.read())["paths"]
                load = retrieval_load(port, queries, seconds, clients)
                probes = probe_loop(port, seconds)
                record = finish_load(load)
            answered = record["statuses"].get("200", 0)
            runs.append(
                {
                    "shards": count,
                    "shard_cpus": shard_cpus,
                    "paths": indexed,
                    "seconds": record["seconds"],
                    "retrievals_per_s": answered / record["seconds"],
                    "retrieve_p50_ms": _ms(record["latencies"], 50),
                    "retrieve_p99_ms": _ms(record["latencies"], 99),
                    "health_p50_ms": _ms(probes["health"], 50),
                    "health_p99_ms": _ms(probes["health"], 99),
                    "simulate_p50_ms": _ms(probes["simulate"], 50),
                    "simulate_p99_ms": _ms(probes["simulate"], 99),
                    "retrieve_statuses": record["statuses"],
                    "probe_statuses": probes["statuses"],
                    "busy_503": record["statuses"].get("503", 0),
                    # The machine's own load meanwhile (other users share it).
                    "load_average_1min": os.getloadavg()[0],
                }
            )
        largest = _largest_bodies(root, port, seconds, no_access_log) if largest_bodies else None
    finally:
        ray.shutdown()
    return {
        "benchmark": "serve",
        "machine": machine_info(),
        "root": root,
        "clients": clients,
        "runs": runs,
        "largest_bodies": largest,
    }


def _largest_bodies(root: str, port: int, seconds: float, logging_config: dict) -> dict:
    """LARGEST_BODY_CLIENTS clients post simulations at the request limits (bodies of
    MAX_BODY_BYTES; one in sixteen a byte over, refused with 413) to one index's app for
    `seconds`, at a lower priority than the server, while another checks health."""
    from links_ray.serve.app import build_app

    body = largest_simulation()["text"]
    bodies = [body] * (2 * LARGEST_BODY_CLIENTS - 1) + [body + " "]
    with _served(build_app(root), port, logging_config):
        load = post_load(port, "/api/simulate", bodies, seconds, LARGEST_BODY_CLIENTS, 10)
        try:
            probes = health_probes(port, seconds)
        finally:
            record = finish_load(load)
    return {
        "clients": LARGEST_BODY_CLIENTS,
        "seconds": record["seconds"],
        "statuses": record["statuses"],
        "simulate_p50_ms": _ms(record["latencies"], 50),
        "health_p50_ms": _ms(probes["latencies"], 50),
        "health_p99_ms": _ms(probes["latencies"], 99),
        "health_max_ms": _ms(probes["latencies"], 100),
        "health_statuses": probes["statuses"],
        "target_health_p99_ms": LARGEST_BODY_HEALTH_P99_TARGET_MS,
        "load_average_1min": os.getloadavg()[0],
    }


@contextlib.contextmanager
def _served(app: Any, port: int, logging_config: dict) -> Iterator[None]:
    """`app` on Serve, its front answering on `port` (once the last run's front has let go of
    it), until the block ends."""
    from ray import serve

    from links_ray.serve.app import bindable_port

    wait_for_port(port)
    serve.start(
        http_options={"host": "127.0.0.1", "port": bindable_port("127.0.0.1", 0)},
        logging_config=logging_config,
    )
    try:
        serve.run(app, name="links", route_prefix="/", logging_config=logging_config)
        yield
    finally:
        serve.shutdown()


def _listening_port() -> int:
    """A free loopback port below Linux's ephemeral range (32768+), for the front to answer on
    run after run: in that range an outgoing connection (Ray opens many as an app starts) may
    take it between two runs."""
    from links_ray.serve.app import bindable_port

    rng = np.random.default_rng()
    for _ in range(200):
        try:
            return bindable_port("127.0.0.1", int(rng.integers(23_000, 30_000)))
        except ValueError:
            continue
    return bindable_port("127.0.0.1", 0)


def format_serve(result: dict) -> str:
    """Throughput and latencies under load, by shard count."""
    rows = []
    for run in result["runs"]:
        other = sum(
            n for status, n in run["retrieve_statuses"].items() if status not in ("200", "503")
        )
        other += sum(n for key, n in run["probe_statuses"].items() if not key.endswith(" 200"))

        def pair(name: str, run: dict = run) -> str:
            p50, p99 = run[f"{name}_p50_ms"], run[f"{name}_p99_ms"]
            return "-" if p50 is None else f"{p50:.1f} / {p99:.1f}"

        rows.append(
            [
                run["shards"] or "none",
                f"{run['retrievals_per_s']:.1f}",
                pair("retrieve"),
                pair("health"),
                pair("simulate"),
                run["busy_503"],
                other,
                f"{run['load_average_1min']:.1f}",
            ]
        )
    header = ["shards", "retrievals/s", "retrieve p50/p99 ms", "health p50/p99 ms"]
    header += ["simulate p50/p99 ms", "503s", "other", "load avg"]
    lines = [
        f"{result['clients']} clients retrieving, one checking health and simulating "
        f"({result['runs'][0]['paths']:,} curated paths)"
        if result["runs"]
        else "no runs",
        report.table(header, rows),
    ]
    largest = result.get("largest_bodies")
    if largest:
        p99, target = largest["health_p99_ms"], largest["target_health_p99_ms"]
        lines.append(
            f"{largest['clients']} clients posting the largest simulations "
            f"({largest['statuses']}, p50 {largest['simulate_p50_ms']:.0f} ms): health "
            f"p50/p99/max {largest['health_p50_ms']:.1f} / {p99:.1f} / "
            f"{largest['health_max_ms']:.1f} ms, target p99 < {target:.0f} ms "
            f"({'met' if p99 < target else 'missed'}; load average "
            f"{largest['load_average_1min']:.1f})"
        )
    return "\n".join(lines)
